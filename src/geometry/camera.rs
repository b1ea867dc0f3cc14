//! Pinhole camera with Brown-Conrady lens distortion (OpenCV's five-term model `k1 k2 p1 p2 k3`).

use nalgebra::{Matrix3, Matrix3x4, Point2, Vector3};
use serde::{Deserialize, Serialize};

/// Pinhole intrinsics in pixels (image origin at the top-left corner, see the module docs) with
/// Brown-Conrady distortion, OpenCV's model, names and order (`k1 k2 p1 p2 k3`), on normalised
/// coordinates `(x, y) = (X/Z, Y/Z)` in the camera frame:
/// `x_d = x(1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2x²)`,
/// `y_d = y(1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2y²) + 2 p2 x y`, then
/// `u = fx x_d + skew y_d + cx`, `v = fy y_d + cy` pixels.
///
/// The one lens model of the project: cameras and projectors, carving, rendering, triangulation,
/// calibration and calibration files all use it. [`Default`] is all zeros, for struct-update syntax
/// (`Intrinsics { fx: 800.0, ..Intrinsics::default() }`); [`Intrinsics::new`] builds a pinhole.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Intrinsics {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Skew (K[0][1]), pixels; 0 for every modern sensor.
    #[serde(default)]
    pub skew: f64,
    /// Radial distortion coefficient of r² (dimensionless).
    #[serde(default)]
    pub k1: f64,
    /// Radial distortion coefficient of r⁴ (dimensionless).
    #[serde(default)]
    pub k2: f64,
    /// First tangential distortion coefficient (dimensionless).
    #[serde(default)]
    pub p1: f64,
    /// Second tangential distortion coefficient (dimensionless).
    #[serde(default)]
    pub p2: f64,
    /// Radial distortion coefficient of r⁶ (dimensionless).
    #[serde(default)]
    pub k3: f64,
}

impl Intrinsics {
    /// A distortion-free pinhole: focal lengths and principal point in pixels, no skew.
    pub fn new(fx: f64, fy: f64, cx: f64, cy: f64) -> Self {
        Intrinsics { fx, fy, cx, cy, ..Intrinsics::default() }
    }

    /// The same intrinsics with OpenCV's distortion vector `(k1, k2, p1, p2, k3)`.
    pub fn with_distortion(self, d: [f64; 5]) -> Self {
        Intrinsics { k1: d[0], k2: d[1], p1: d[2], p2: d[3], k3: d[4], ..self }
    }

    /// OpenCV's distortion vector `(k1, k2, p1, p2, k3)`.
    pub fn distortion(&self) -> [f64; 5] {
        [self.k1, self.k2, self.p1, self.p2, self.k3]
    }

    /// The 3x3 calibration matrix K.
    pub fn matrix(&self) -> Matrix3<f64> {
        Matrix3::new(self.fx, self.skew, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }

    /// From a 3x3 K (no distortion).
    pub fn from_matrix(k: &Matrix3<f64>) -> Self {
        let s = k[(2, 2)];
        Intrinsics {
            fx: k[(0, 0)] / s,
            fy: k[(1, 1)] / s,
            cx: k[(0, 2)] / s,
            cy: k[(1, 2)] / s,
            skew: k[(0, 1)] / s,
            ..Intrinsics::default()
        }
    }

    /// The same intrinsics without distortion.
    pub fn pinhole(&self) -> Intrinsics {
        Intrinsics { fx: self.fx, fy: self.fy, cx: self.cx, cy: self.cy, skew: self.skew, ..Intrinsics::default() }
    }

    /// True when any distortion coefficient is non-zero.
    pub fn has_distortion(&self) -> bool {
        self.distortion().iter().any(|&d| d != 0.0)
    }

    /// True when every value is finite and both focal lengths are positive.
    pub fn is_valid(&self) -> bool {
        [self.fx, self.fy, self.cx, self.cy, self.skew].iter().chain(self.distortion().iter()).all(|v| v.is_finite())
            && self.fx > 0.0
            && self.fy > 0.0
    }

    /// Apply distortion to normalised coordinates.
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        (
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// Invert [`Intrinsics::distort`] by fixed-point iteration, as OpenCV's `undistortPoints` does
    /// (converges for real lenses within their field of view).
    pub fn undistort(&self, xd: f64, yd: f64) -> (f64, f64) {
        if !self.has_distortion() {
            return (xd, yd);
        }
        let (mut x, mut y) = (xd, yd);
        for _ in 0..30 {
            let r2 = x * x + y * y;
            let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
            let dx = 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x);
            let dy = self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y;
            x = (xd - dx) / radial;
            y = (yd - dy) / radial;
        }
        (x, y)
    }

    /// Normalised (distortion-free) coordinates to pixels, applying distortion.
    pub fn normalised_to_pixel(&self, x: f64, y: f64) -> Point2<f64> {
        let (xd, yd) = self.distort(x, y);
        Point2::new(self.fx * xd + self.skew * yd + self.cx, self.fy * yd + self.cy)
    }

    /// Pixel coordinates to undistorted normalised coordinates.
    pub fn pixel_to_normalised(&self, u: f64, v: f64) -> (f64, f64) {
        let yd = (v - self.cy) / self.fy;
        let xd = (u - self.cx - self.skew * yd) / self.fx;
        self.undistort(xd, yd)
    }
}

/// Rigid transform from a reference frame (rig or object frame) to the camera frame:
/// `x_cam = rotation · x_ref + translation`, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Rotation reference -> camera.
    pub rotation: Matrix3<f64>,
    /// Translation, metres (the reference origin expressed in the camera frame).
    pub translation: Vector3<f64>,
}

impl Pose {
    /// A camera at `eye` looking at `target` with `up` pointing up in the image (all in the reference
    /// frame, metres). Camera `+z` points from eye to target, `+y` points down in the image.
    pub fn look_at(eye: Vector3<f64>, target: Vector3<f64>, up: Vector3<f64>) -> Pose {
        let z = (target - eye).normalize();
        let x = z.cross(&up).normalize();
        let y = z.cross(&x);
        let rotation = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
        Pose { rotation, translation: -(rotation * eye) }
    }

    /// Camera centre in the reference frame, metres.
    pub fn centre(&self) -> Vector3<f64> {
        -(self.rotation.transpose() * self.translation)
    }

    /// Transform a reference-frame point into the camera frame.
    pub fn apply(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * p + self.translation
    }

    /// The same camera seen from the object frame when the turntable is at `degrees`:
    /// `x_cam = R · Rz(θ) · x_obj + t`.
    pub fn for_turntable_angle(&self, degrees: f64) -> Pose {
        Pose { rotation: self.rotation * super::turntable_rotation(degrees), translation: self.translation }
    }
}

/// A calibrated camera: image size in pixels, intrinsics, and pose (reference frame -> camera).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraModel {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Intrinsics, pixels.
    pub intrinsics: Intrinsics,
    /// Pose, reference frame -> camera frame.
    pub pose: Pose,
}

impl CameraModel {
    /// Project a reference-frame point (metres) to continuous pixel coordinates, applying distortion.
    /// `None` when the point is not in front of the camera.
    pub fn project(&self, p: &Vector3<f64>) -> Option<Point2<f64>> {
        let c = self.pose.apply(p);
        if c.z <= 0.0 {
            return None;
        }
        Some(self.intrinsics.normalised_to_pixel(c.x / c.z, c.y / c.z))
    }

    /// The pixel a reference-frame point falls in, if it is in front of the camera and inside the image.
    pub fn pixel_of(&self, p: &Vector3<f64>) -> Option<(u32, u32)> {
        let q = self.project(p)?;
        let (u, v) = (super::round::floor_f64(q.x), super::round::floor_f64(q.y));
        (u >= 0.0 && v >= 0.0 && u < self.width as f64 && v < self.height as f64).then_some((u as u32, v as u32))
    }

    /// `P = K [R | t]`, ignoring distortion.
    pub fn projection_matrix(&self) -> Matrix3x4<f64> {
        let mut rt = Matrix3x4::zeros();
        rt.fixed_view_mut::<3, 3>(0, 0).copy_from(&self.pose.rotation);
        rt.fixed_view_mut::<3, 1>(0, 3).copy_from(&self.pose.translation);
        self.intrinsics.matrix() * rt
    }

    /// Unit ray direction in the reference frame through continuous pixel coordinates `(u, v)`.
    pub fn pixel_ray(&self, u: f64, v: f64) -> Vector3<f64> {
        let (x, y) = self.intrinsics.pixel_to_normalised(u, v);
        (self.pose.rotation.transpose() * Vector3::new(x, y, 1.0)).normalize()
    }

    /// Camera centre in the reference frame, metres.
    pub fn centre(&self) -> Vector3<f64> {
        self.pose.centre()
    }

    /// True when every intrinsic and pose value is finite (no NaN or infinity from a bad file).
    pub fn is_finite(&self) -> bool {
        let i = &self.intrinsics;
        [i.fx, i.fy, i.cx, i.cy, i.skew].iter().chain(i.distortion().iter()).all(|x| x.is_finite())
            && self.pose.rotation.iter().all(|x| x.is_finite())
            && self.pose.translation.iter().all(|x| x.is_finite())
    }

    /// This camera expressed in the object frame when the turntable is at `degrees`
    /// (the camera's pose is given in the rig frame).
    pub fn for_turntable_angle(&self, degrees: f64) -> CameraModel {
        CameraModel { pose: self.pose.for_turntable_angle(degrees), ..*self }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> CameraModel {
        CameraModel {
            width: 640,
            height: 480,
            intrinsics: Intrinsics::new(800.0, 800.0, 320.0, 240.0).with_distortion([-0.1, 0.01, 1e-3, -2e-3, 0.02]),
            pose: Pose::look_at(Vector3::new(0.0, -0.5, 0.2), Vector3::new(0.0, 0.0, 0.05), Vector3::z()),
        }
    }

    #[test]
    fn look_at_centres_the_target() {
        let c = cam();
        let q = c.project(&Vector3::new(0.0, 0.0, 0.05)).expect("in front");
        assert!((q.x - 320.0).abs() < 1e-9 && (q.y - 240.0).abs() < 1e-9);
        // Up in the world is up in the image (smaller v).
        let up = c.project(&Vector3::new(0.0, 0.0, 0.1)).expect("in front");
        assert!(up.y < 240.0);
        assert!((c.centre() - Vector3::new(0.0, -0.5, 0.2)).norm() < 1e-12);
    }

    #[test]
    fn pixel_ray_inverts_projection_with_distortion() {
        let c = cam();
        let p = Vector3::new(0.03, 0.02, 0.09);
        let q = c.project(&p).expect("in front");
        let ray = c.pixel_ray(q.x, q.y);
        let expected = (p - c.centre()).normalize();
        assert!((ray - expected).norm() < 1e-9, "{ray} vs {expected}");
    }

    #[test]
    fn projection_matrix_matches_project_without_distortion() {
        let mut c = cam();
        c.intrinsics = c.intrinsics.pinhole();
        let p = Vector3::new(0.01, -0.02, 0.03);
        let h = c.projection_matrix() * p.push(1.0);
        let q = c.project(&p).expect("in front");
        assert!((h.x / h.z - q.x).abs() < 1e-9 && (h.y / h.z - q.y).abs() < 1e-9);
    }
}

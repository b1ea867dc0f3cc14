//! Camera models, projection and rigid transforms (nalgebra).
//!
//! # Coordinate frames
//! - **Rig frame**: fixed to the rig. Origin on the turntable axis at the table top, `+z` up along the
//!   axis, `x`/`y` horizontal. Metres. Cameras, lights, lasers and the projector are posed in it.
//! - **Object frame**: fixed to the turntable top. It coincides with the rig frame at turntable angle 0;
//!   at angle `θ` (degrees, counter-clockwise seen from above, i.e. right-handed about `+z`) a point
//!   `p_obj` is at `Rz(θ)·p_obj` in the rig frame. Reconstruction happens in the object frame.
//! - **Camera frame**: OpenCV convention, `+z` forward along the optical axis, `+x` right, `+y` down.
//! - **Image**: pixels, origin at the top-left corner of the image; pixel `(u, v)` covers
//!   `[u, u+1) × [v, v+1)`, so a projected point `(x, y)` falls in pixel `(floor x, floor y)`.

mod camera;
mod grid;
pub(crate) mod round;

pub use camera::{CameraModel, Intrinsics, Pose};
pub use grid::VoxelGrid;
pub use nalgebra::{Matrix3, Matrix3x4, Point2, Point3, Vector3};

/// Rotation about the turntable axis (`+z`) by `degrees`, counter-clockwise seen from above.
pub fn turntable_rotation(degrees: f64) -> Matrix3<f64> {
    let (s, c) = degrees.to_radians().sin_cos();
    Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)
}

/// An axis-aligned box in metres, in whatever frame its owner says (usually the object frame).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Aabb {
    /// Minimum corner, metres.
    pub min: [f64; 3],
    /// Maximum corner, metres.
    pub max: [f64; 3],
}

impl Aabb {
    /// Edge lengths in metres.
    pub fn extent(&self) -> [f64; 3] {
        [self.max[0] - self.min[0], self.max[1] - self.min[1], self.max[2] - self.min[2]]
    }

    /// Length of the diagonal in metres.
    pub fn diagonal(&self) -> f64 {
        let e = self.extent();
        (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]).sqrt()
    }

    /// The eight corners.
    pub fn corners(&self) -> [Vector3<f64>; 8] {
        let mut out = [Vector3::zeros(); 8];
        for (i, c) in out.iter_mut().enumerate() {
            *c = Vector3::new(
                if i & 1 == 0 { self.min[0] } else { self.max[0] },
                if i & 2 == 0 { self.min[1] } else { self.max[1] },
                if i & 4 == 0 { self.min[2] } else { self.max[2] },
            );
        }
        out
    }

    /// True when every edge is finite and strictly positive.
    pub fn is_valid(&self) -> bool {
        (0..3).all(|i| self.min[i].is_finite() && self.max[i].is_finite() && self.max[i] > self.min[i])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn turntable_rotation_is_counter_clockwise_from_above() {
        let p = turntable_rotation(90.0) * Vector3::new(1.0, 0.0, 0.0);
        assert!((p - Vector3::new(0.0, 1.0, 0.0)).norm() < 1e-12);
    }
}

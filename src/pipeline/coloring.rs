//! Per-vertex colours for a mesh from calibrated RGB images.
//!
//! Each vertex takes the colour of the pixel it projects to in the view that faces it most directly:
//! the view maximising the cosine between the vertex normal (area-weighted average of the adjacent
//! triangles' normals, pointing out of the object) and the direction from the vertex to the camera
//! centre, among the views where the vertex projects inside the image. There is no occlusion test, so
//! concave regions may take a colour from a surface in front of them. Vertices no view sees stay grey.

use image::RgbImage;
use nalgebra::Vector3;
use rayon::prelude::*;

use super::mesh::TriangleMesh;
use crate::geometry::CameraModel;

/// A camera (in the mesh's frame) and its RGB image (same size as the camera's image).
#[derive(Debug, Clone, Copy)]
pub struct ColorView<'a> {
    /// The camera, in the mesh's frame.
    pub camera: CameraModel,
    /// The image it took.
    pub image: &'a RgbImage,
}

/// Colour of vertices that no view sees.
pub const UNSEEN_COLOR: [u8; 3] = [128, 128, 128];

/// Outward vertex normals (unit length, zero for isolated vertices).
pub fn vertex_normals(mesh: &TriangleMesh) -> Vec<[f32; 3]> {
    let mut acc = vec![Vector3::<f64>::zeros(); mesh.vertices.len()];
    for t in &mesh.triangles {
        let p = t.map(|i| mesh.vertices.get(i as usize).map(|v| Vector3::new(v[0] as f64, v[1] as f64, v[2] as f64)));
        if let [Some(a), Some(b), Some(c)] = p {
            let n = (b - a).cross(&(c - a));
            for &i in t {
                acc[i as usize] += n;
            }
        }
    }
    acc.iter()
        .map(|n| {
            let l = n.norm();
            if l > 0.0 {
                [(n.x / l) as f32, (n.y / l) as f32, (n.z / l) as f32]
            } else {
                [0.0; 3]
            }
        })
        .collect()
}

/// Colours for the mesh's vertices (see the module docs); views whose image size differs from their
/// camera's are ignored.
pub fn color_vertices(mesh: &TriangleMesh, views: &[ColorView<'_>]) -> Vec<[u8; 3]> {
    let normals = vertex_normals(mesh);
    let views: Vec<&ColorView<'_>> =
        views.iter().filter(|v| v.image.dimensions() == (v.camera.width, v.camera.height)).collect();
    let centres: Vec<Vector3<f64>> = views.iter().map(|v| v.camera.centre()).collect();
    mesh.vertices
        .par_iter()
        .zip(normals.par_iter())
        .map(|(p, n)| {
            let p = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            let n = Vector3::new(n[0] as f64, n[1] as f64, n[2] as f64);
            let mut best: Option<(f64, [u8; 3])> = None;
            for (v, c) in views.iter().zip(&centres) {
                let Some((u, w)) = v.camera.pixel_of(&p) else { continue };
                let cos = n.dot(&(c - p).normalize());
                if best.is_none_or(|(b, _)| cos > b) {
                    best = Some((cos, v.image.get_pixel(u, w).0));
                }
            }
            best.map(|(_, c)| c).unwrap_or(UNSEEN_COLOR)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Intrinsics, Pose};

    #[test]
    fn each_vertex_takes_the_colour_of_the_camera_it_faces() {
        // Two vertices with opposite normals (two thin triangles back to back are not needed:
        // normals come from the triangles, so build one triangle per side).
        let mesh = TriangleMesh {
            vertices: vec![
                [0.1, 0.0, 0.0],
                [0.1, 0.01, 0.0],
                [0.1, 0.0, 0.01],
                [-0.1, 0.0, 0.0],
                [-0.1, 0.0, 0.01],
                [-0.1, 0.01, 0.0],
            ],
            triangles: vec![[0, 1, 2], [3, 4, 5]],
            colors: None,
        };
        let intr = Intrinsics {
            fx: 100.0,
            fy: 100.0,
            cx: 50.0,
            cy: 50.0,
            skew: 0.0,
            k1: 0.0,
            k2: 0.0,
            ..Intrinsics::default()
        };
        let cam = |x: f64| CameraModel {
            width: 100,
            height: 100,
            intrinsics: intr,
            pose: Pose::look_at(Vector3::new(x, 0.0, 0.0), Vector3::zeros(), Vector3::z()),
        };
        let red = RgbImage::from_pixel(100, 100, image::Rgb([255, 0, 0]));
        let blue = RgbImage::from_pixel(100, 100, image::Rgb([0, 0, 255]));
        let views = [ColorView { camera: cam(1.0), image: &red }, ColorView { camera: cam(-1.0), image: &blue }];
        let c = color_vertices(&mesh, &views);
        assert_eq!(c[0], [255, 0, 0]);
        assert_eq!(c[3], [0, 0, 255]);
        let n = vertex_normals(&mesh);
        assert!(n[0][0] > 0.99 && n[3][0] < -0.99);
    }
}

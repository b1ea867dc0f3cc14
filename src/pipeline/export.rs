//! Writers for meshes and point clouds: binary little-endian PLY, binary STL, OBJ.
//!
//! Every file is written atomically: the bytes go to a temporary file in the same directory, which is
//! flushed to disk (fsync) and then renamed over the destination, so a reader never sees a partial file.
//! Coordinates are written as they are stored (metres, the grid's frame).

use std::path::{Path, PathBuf};

use crate::atomic::{write_atomic, AtomicWriteError};

use super::mesh::TriangleMesh;
use super::occupancy::Occupancy;

/// Errors of the writers; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// Creating, writing, syncing or renaming failed.
    #[error("cannot write {path}")]
    Io {
        /// The destination file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// Colours were given but not one per vertex / point.
    #[error("{path}: {colors} colours for {items} vertices or points")]
    ColorCount {
        /// The destination file.
        path: PathBuf,
        /// Colours given.
        colors: usize,
        /// Vertices or points.
        items: usize,
    },
}

impl From<AtomicWriteError> for ExportError {
    fn from(e: AtomicWriteError) -> Self {
        ExportError::Io { path: e.path, source: e.source }
    }
}

fn check_colors(path: &Path, colors: Option<&Vec<[u8; 3]>>, items: usize) -> Result<(), ExportError> {
    match colors {
        Some(c) if c.len() != items => {
            Err(ExportError::ColorCount { path: path.to_path_buf(), colors: c.len(), items })
        }
        _ => Ok(()),
    }
}

/// Encode a mesh as binary little-endian PLY (`vertex` x y z float, optional red green blue uchar;
/// `face` with a uchar count and uint indices).
pub fn ply_mesh_bytes(mesh: &TriangleMesh) -> Vec<u8> {
    let color = mesh.colors.as_ref().filter(|c| c.len() == mesh.vertices.len());
    let mut out = Vec::with_capacity(200 + mesh.vertices.len() * 15 + mesh.triangles.len() * 13);
    out.extend_from_slice(b"ply\nformat binary_little_endian 1.0\ncomment scanrig\n");
    out.extend_from_slice(format!("element vertex {}\n", mesh.vertices.len()).as_bytes());
    out.extend_from_slice(b"property float x\nproperty float y\nproperty float z\n");
    if color.is_some() {
        out.extend_from_slice(b"property uchar red\nproperty uchar green\nproperty uchar blue\n");
    }
    out.extend_from_slice(format!("element face {}\n", mesh.triangles.len()).as_bytes());
    out.extend_from_slice(b"property list uchar uint vertex_indices\nend_header\n");
    for (n, v) in mesh.vertices.iter().enumerate() {
        for c in v {
            out.extend_from_slice(&c.to_le_bytes());
        }
        if let Some(cs) = color {
            out.extend_from_slice(&cs[n]);
        }
    }
    for t in &mesh.triangles {
        out.push(3);
        for i in t {
            out.extend_from_slice(&i.to_le_bytes());
        }
    }
    out
}

/// Write a mesh as binary PLY, atomically.
pub fn write_ply_mesh(path: &Path, mesh: &TriangleMesh) -> Result<(), ExportError> {
    check_colors(path, mesh.colors.as_ref(), mesh.vertices.len())?;
    Ok(write_atomic(path, &ply_mesh_bytes(mesh))?)
}

/// Encode a mesh as binary STL (80-byte header, count, per triangle a facet normal and three vertices).
pub fn stl_bytes(mesh: &TriangleMesh) -> Vec<u8> {
    let mut out = Vec::with_capacity(84 + 50 * mesh.triangles.len());
    let mut header = [0u8; 80];
    let text = b"binary STL written by scanrig, metres";
    header[..text.len()].copy_from_slice(text);
    out.extend_from_slice(&header);
    out.extend_from_slice(&(mesh.triangles.len() as u32).to_le_bytes());
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| mesh.vertices.get(i as usize).copied().unwrap_or([0.0; 3]));
        let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
        let mut n = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        if len > 0.0 {
            n = n.map(|x| x / len);
        }
        for p in [n, a, b, c] {
            for x in p {
                out.extend_from_slice(&x.to_le_bytes());
            }
        }
        out.extend_from_slice(&[0, 0]);
    }
    out
}

/// Write a mesh as binary STL, atomically (colours are not stored).
pub fn write_stl(path: &Path, mesh: &TriangleMesh) -> Result<(), ExportError> {
    Ok(write_atomic(path, &stl_bytes(mesh))?)
}

/// Encode a mesh as OBJ text (`v x y z` or `v x y z r g b` with colours in 0..1, `f` 1-based).
pub fn obj_bytes(mesh: &TriangleMesh) -> Vec<u8> {
    use std::fmt::Write as _;
    let color = mesh.colors.as_ref().filter(|c| c.len() == mesh.vertices.len());
    let mut s = String::with_capacity(mesh.vertices.len() * 40 + mesh.triangles.len() * 24);
    s.push_str("# written by scanrig, metres\n");
    for (n, v) in mesh.vertices.iter().enumerate() {
        let _ = write!(s, "v {} {} {}", v[0], v[1], v[2]);
        if let Some(cs) = color {
            let c = cs[n].map(|x| x as f32 / 255.0);
            let _ = write!(s, " {} {} {}", c[0], c[1], c[2]);
        }
        s.push('\n');
    }
    for t in &mesh.triangles {
        let _ = writeln!(s, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    s.into_bytes()
}

/// Write a mesh as OBJ, atomically.
pub fn write_obj(path: &Path, mesh: &TriangleMesh) -> Result<(), ExportError> {
    check_colors(path, mesh.colors.as_ref(), mesh.vertices.len())?;
    Ok(write_atomic(path, &obj_bytes(mesh))?)
}

/// Encode points as a binary little-endian PLY point cloud (optional RGB).
pub fn ply_points_bytes(points: &[[f32; 3]], colors: Option<&Vec<[u8; 3]>>) -> Vec<u8> {
    let color = colors.filter(|c| c.len() == points.len());
    let mut out = Vec::with_capacity(200 + points.len() * 15);
    out.extend_from_slice(b"ply\nformat binary_little_endian 1.0\ncomment scanrig\n");
    out.extend_from_slice(format!("element vertex {}\n", points.len()).as_bytes());
    out.extend_from_slice(b"property float x\nproperty float y\nproperty float z\n");
    if color.is_some() {
        out.extend_from_slice(b"property uchar red\nproperty uchar green\nproperty uchar blue\n");
    }
    out.extend_from_slice(b"end_header\n");
    for (n, p) in points.iter().enumerate() {
        for c in p {
            out.extend_from_slice(&c.to_le_bytes());
        }
        if let Some(cs) = color {
            out.extend_from_slice(&cs[n]);
        }
    }
    out
}

/// Write points as a binary PLY point cloud, atomically.
pub fn write_ply_points(path: &Path, points: &[[f32; 3]], colors: Option<&Vec<[u8; 3]>>) -> Result<(), ExportError> {
    check_colors(path, colors, points.len())?;
    Ok(write_atomic(path, &ply_points_bytes(points, colors))?)
}

/// The centres of the occupied voxels, metres (the grid's frame).
pub fn voxel_centres(occupancy: &Occupancy) -> Vec<[f32; 3]> {
    let g = occupancy.grid();
    let mut out = Vec::new();
    occupancy.for_each_occupied(|i, j, k| {
        let c = g.centre(i, j, k);
        out.push([c.x as f32, c.y as f32, c.z as f32]);
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tet() -> TriangleMesh {
        TriangleMesh {
            vertices: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            triangles: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
            colors: Some(vec![[255, 0, 0], [0, 255, 0], [0, 0, 255], [9, 9, 9]]),
        }
    }

    #[test]
    fn ply_mesh_layout_and_atomic_write() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("m.ply");
        let m = tet();
        write_ply_mesh(&path, &m).expect("write");
        let bytes = std::fs::read(&path).expect("read");
        let end = bytes.windows(11).position(|w| w == b"end_header\n").expect("header") + 11;
        assert_eq!(bytes.len() - end, 4 * 15 + 4 * 13);
        let header = std::str::from_utf8(&bytes[..end]).expect("ascii header");
        assert!(header.contains("element vertex 4") && header.contains("property uchar red"));
        assert_eq!(f32::from_le_bytes(bytes[end + 15..end + 19].try_into().expect("4 bytes")), 1.0);
        // No temporary file is left behind.
        assert_eq!(std::fs::read_dir(dir.path()).expect("dir").count(), 1);
        assert!(m.signed_volume() > 0.0);
    }

    #[test]
    fn stl_and_obj_and_points() {
        let m = tet();
        let stl = stl_bytes(&m);
        assert_eq!(stl.len(), 84 + 50 * 4);
        assert_eq!(u32::from_le_bytes(stl[80..84].try_into().expect("4 bytes")), 4);
        let obj = String::from_utf8(obj_bytes(&m)).expect("utf8");
        assert!(obj.contains("v 1 0 0 0 1 0\n") && obj.contains("f 2 3 4\n"));
        let pts = ply_points_bytes(&m.vertices, None);
        assert!(pts.ends_with(&1.0f32.to_le_bytes()));
    }

    #[test]
    fn errors_name_the_file() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("no-such-dir").join("x.stl");
        let e = write_stl(&path, &tet()).expect_err("missing directory");
        assert!(e.to_string().contains("x.stl"));
        let mut m = tet();
        m.colors = Some(vec![[0, 0, 0]]);
        let e = write_obj(&dir.path().join("c.obj"), &m).expect_err("colour count");
        assert!(matches!(e, ExportError::ColorCount { colors: 1, items: 4, .. }));
    }
}

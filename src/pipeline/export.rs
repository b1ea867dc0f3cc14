//! Writers for meshes and point clouds: binary little-endian PLY, binary STL, OBJ.
//!
//! Every file is written atomically and streamed: the records go through a buffer to a temporary file
//! in the same directory, which is flushed to disk (fsync) and then renamed over the destination, so a
//! reader never sees a partial file and no file is held whole in memory.
//! Coordinates are written as they are stored (metres, the grid's frame).

use std::io::Write;
use std::path::{Path, PathBuf};

use crate::atomic::{write_atomic_with, AtomicWriteError};

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
/// `face` with a uchar count and uint indices) into `w`, record by record.
pub fn encode_ply_mesh<W: Write>(w: &mut W, mesh: &TriangleMesh) -> std::io::Result<()> {
    let color = mesh.colors.as_ref().filter(|c| c.len() == mesh.vertices.len());
    w.write_all(b"ply\nformat binary_little_endian 1.0\ncomment scanrig\n")?;
    writeln!(w, "element vertex {}", mesh.vertices.len())?;
    w.write_all(b"property float x\nproperty float y\nproperty float z\n")?;
    if color.is_some() {
        w.write_all(b"property uchar red\nproperty uchar green\nproperty uchar blue\n")?;
    }
    writeln!(w, "element face {}", mesh.triangles.len())?;
    w.write_all(b"property list uchar uint vertex_indices\nend_header\n")?;
    for (n, v) in mesh.vertices.iter().enumerate() {
        write_point(w, v, color.map(|c| &c[n]))?;
    }
    for t in &mesh.triangles {
        let mut rec = [3u8; 13];
        for (a, i) in t.iter().enumerate() {
            rec[1 + 4 * a..5 + 4 * a].copy_from_slice(&i.to_le_bytes());
        }
        w.write_all(&rec)?;
    }
    Ok(())
}

/// One PLY vertex record: x y z (float) and, if given, red green blue (uchar).
fn write_point<W: Write>(w: &mut W, p: &[f32; 3], color: Option<&[u8; 3]>) -> std::io::Result<()> {
    let mut rec = [0u8; 15];
    for (a, x) in p.iter().enumerate() {
        rec[4 * a..4 * a + 4].copy_from_slice(&x.to_le_bytes());
    }
    match color {
        Some(c) => {
            rec[12..].copy_from_slice(c);
            w.write_all(&rec)
        }
        None => w.write_all(&rec[..12]),
    }
}

/// Everything [`encode_ply_mesh`] writes, in memory (for a download of a small mesh).
pub fn ply_mesh_bytes(mesh: &TriangleMesh) -> Vec<u8> {
    let mut out = Vec::with_capacity(200 + mesh.vertices.len() * 15 + mesh.triangles.len() * 13);
    encode_ply_mesh(&mut out, mesh).expect("writing into memory cannot fail");
    out
}

/// Write a mesh as binary PLY, atomically, streamed to the file.
pub fn write_ply_mesh(path: &Path, mesh: &TriangleMesh) -> Result<(), ExportError> {
    check_colors(path, mesh.colors.as_ref(), mesh.vertices.len())?;
    Ok(write_atomic_with(path, |w| encode_ply_mesh(w, mesh))?)
}

/// Encode a mesh as binary STL (80-byte header, count, per triangle a facet normal and three
/// vertices) into `w`.
pub fn encode_stl<W: Write>(w: &mut W, mesh: &TriangleMesh) -> std::io::Result<()> {
    let mut header = [0u8; 80];
    let text = b"binary STL written by scanrig, metres";
    header[..text.len()].copy_from_slice(text);
    w.write_all(&header)?;
    w.write_all(&(mesh.triangles.len() as u32).to_le_bytes())?;
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| mesh.vertices.get(i as usize).copied().unwrap_or([0.0; 3]));
        let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
        let mut n = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        if len > 0.0 {
            n = n.map(|x| x / len);
        }
        let mut rec = [0u8; 50];
        for (q, p) in [n, a, b, c].iter().enumerate() {
            for (a, x) in p.iter().enumerate() {
                rec[12 * q + 4 * a..12 * q + 4 * a + 4].copy_from_slice(&x.to_le_bytes());
            }
        }
        w.write_all(&rec)?;
    }
    Ok(())
}

/// Write a mesh as binary STL, atomically, streamed to the file (colours are not stored).
pub fn write_stl(path: &Path, mesh: &TriangleMesh) -> Result<(), ExportError> {
    Ok(write_atomic_with(path, |w| encode_stl(w, mesh))?)
}

/// Encode a mesh as OBJ text (`v x y z` or `v x y z r g b` with colours in 0..1, `f` 1-based) into `w`.
pub fn encode_obj<W: Write>(w: &mut W, mesh: &TriangleMesh) -> std::io::Result<()> {
    let color = mesh.colors.as_ref().filter(|c| c.len() == mesh.vertices.len());
    w.write_all(b"# written by scanrig, metres\n")?;
    for (n, v) in mesh.vertices.iter().enumerate() {
        write!(w, "v {} {} {}", v[0], v[1], v[2])?;
        if let Some(cs) = color {
            let c = cs[n].map(|x| x as f32 / 255.0);
            write!(w, " {} {} {}", c[0], c[1], c[2])?;
        }
        w.write_all(b"\n")?;
    }
    for t in &mesh.triangles {
        writeln!(w, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1)?;
    }
    Ok(())
}

/// Write a mesh as OBJ, atomically, streamed to the file.
pub fn write_obj(path: &Path, mesh: &TriangleMesh) -> Result<(), ExportError> {
    check_colors(path, mesh.colors.as_ref(), mesh.vertices.len())?;
    Ok(write_atomic_with(path, |w| encode_obj(w, mesh))?)
}

/// The header of a binary little-endian PLY point cloud of `count` points (optional RGB).
fn write_points_header<W: Write>(w: &mut W, count: u64, color: bool) -> std::io::Result<()> {
    w.write_all(b"ply\nformat binary_little_endian 1.0\ncomment scanrig\n")?;
    writeln!(w, "element vertex {count}")?;
    w.write_all(b"property float x\nproperty float y\nproperty float z\n")?;
    if color {
        w.write_all(b"property uchar red\nproperty uchar green\nproperty uchar blue\n")?;
    }
    w.write_all(b"end_header\n")
}

/// Encode points as a binary little-endian PLY point cloud (optional RGB, one colour per point)
/// into `w`.
pub fn encode_ply_points<W: Write>(
    w: &mut W,
    points: &[[f32; 3]],
    colors: Option<&Vec<[u8; 3]>>,
) -> std::io::Result<()> {
    let color = colors.filter(|c| c.len() == points.len());
    write_points_header(w, points.len() as u64, color.is_some())?;
    for (n, p) in points.iter().enumerate() {
        write_point(w, p, color.map(|c| &c[n]))?;
    }
    Ok(())
}

/// Everything [`encode_ply_points`] writes, in memory (for a download of a small cloud).
pub fn ply_points_bytes(points: &[[f32; 3]], colors: Option<&Vec<[u8; 3]>>) -> Vec<u8> {
    let mut out = Vec::with_capacity(200 + points.len() * 15);
    encode_ply_points(&mut out, points, colors).expect("writing into memory cannot fail");
    out
}

/// Write points as a binary PLY point cloud, atomically, streamed to the file.
pub fn write_ply_points(path: &Path, points: &[[f32; 3]], colors: Option<&Vec<[u8; 3]>>) -> Result<(), ExportError> {
    check_colors(path, colors, points.len())?;
    Ok(write_atomic_with(path, |w| encode_ply_points(w, points, colors))?)
}

/// Encode the centres of the `count` occupied voxels (metres, the grid's frame) as a binary PLY
/// point cloud into `w`, in [`Occupancy::for_each_occupied`]'s order, straight from the bricks: no
/// list of the centres is built, so the memory it takes does not grow with the solid's volume.
/// `colors`, if given, holds one colour per occupied voxel in that order.
fn encode_ply_voxels<W: Write>(
    w: &mut W,
    occupancy: &Occupancy,
    count: u64,
    colors: Option<&Vec<[u8; 3]>>,
) -> std::io::Result<()> {
    let color = colors.filter(|c| c.len() as u64 == count);
    write_points_header(w, count, color.is_some())?;
    let g = occupancy.grid();
    let mut n = 0;
    let mut result = Ok(());
    occupancy.for_each_occupied(|i, j, k| {
        if result.is_ok() {
            let c = g.centre(i, j, k);
            result = write_point(w, &[c.x as f32, c.y as f32, c.z as f32], color.map(|cs| &cs[n]));
        }
        n += 1;
    });
    result
}

/// Write the occupied voxels' centres as a binary PLY point cloud, atomically, streamed to the
/// file (see `encode_ply_voxels`).
pub fn write_ply_voxels(path: &Path, occupancy: &Occupancy, colors: Option<&Vec<[u8; 3]>>) -> Result<(), ExportError> {
    let count = occupancy.count();
    if let Some(c) = colors.filter(|c| c.len() as u64 != count) {
        return Err(ExportError::ColorCount { path: path.to_path_buf(), colors: c.len(), items: count as usize });
    }
    Ok(write_atomic_with(path, |w| encode_ply_voxels(w, occupancy, count, colors))?)
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
        let mut stl = Vec::new();
        encode_stl(&mut stl, &m).expect("in memory");
        assert_eq!(stl.len(), 84 + 50 * 4);
        assert_eq!(u32::from_le_bytes(stl[80..84].try_into().expect("4 bytes")), 4);
        let mut obj = Vec::new();
        encode_obj(&mut obj, &m).expect("in memory");
        let obj = String::from_utf8(obj).expect("utf8");
        assert!(obj.contains("v 1 0 0 0 1 0\n") && obj.contains("f 2 3 4\n"));
        let pts = ply_points_bytes(&m.vertices, None);
        assert!(pts.ends_with(&1.0f32.to_le_bytes()));
    }

    #[test]
    fn voxels_stream_from_the_bricks_as_their_centres_would_be_written() {
        use crate::geometry::VoxelGrid;
        let grid = VoxelGrid { origin: [-0.1, 0.2, 0.0], voxel_size: 0.01, dims: [19, 11, 13] };
        let occ = Occupancy::from_index_fn(grid, |i, j, k| (i * 7 + j * 3 + k * 5) % 4 != 0 && i + j < 25);
        let mut centres = Vec::new();
        occ.for_each_occupied(|i, j, k| {
            let c = grid.centre(i, j, k);
            centres.push([c.x as f32, c.y as f32, c.z as f32]);
        });
        assert!(centres.len() > 1000 && (centres.len() as u64) < grid.len() as u64);
        let colours: Vec<[u8; 3]> = (0..centres.len()).map(|n| [n as u8, (n / 256) as u8, 7]).collect();
        let dir = tempfile::tempdir().expect("tempdir");
        for colours in [None, Some(&colours)] {
            let path = dir.path().join("voxels.ply");
            write_ply_voxels(&path, &occ, colours).expect("write");
            assert_eq!(std::fs::read(&path).expect("read"), ply_points_bytes(&centres, colours));
        }
        let short = colours[1..].to_vec();
        let e = write_ply_voxels(&dir.path().join("bad.ply"), &occ, Some(&short)).expect_err("colour count");
        assert!(e.to_string().contains("bad.ply"), "{e}");
        assert!(matches!(e, ExportError::ColorCount { items, .. } if items == centres.len()));
        assert_eq!(std::fs::read_dir(dir.path()).expect("dir").count(), 1, "only voxels.ply");
    }

    #[test]
    fn streamed_files_are_the_encoded_bytes() {
        let dir = tempfile::tempdir().expect("tempdir");
        let m = tet();
        let path = dir.path().join("m.ply");
        write_ply_mesh(&path, &m).expect("ply");
        assert_eq!(std::fs::read(&path).expect("read"), ply_mesh_bytes(&m));
        let mut expected = Vec::new();
        encode_stl(&mut expected, &m).expect("in memory");
        write_stl(&path, &m).expect("stl");
        assert_eq!(std::fs::read(&path).expect("read"), expected);
        let mut expected = Vec::new();
        encode_obj(&mut expected, &m).expect("in memory");
        write_obj(&path, &m).expect("obj");
        assert_eq!(std::fs::read(&path).expect("read"), expected);
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

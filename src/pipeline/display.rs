//! Models made small enough for a viewer: a mesh decimated by vertex clustering to at most a number
//! of faces, a point cloud subsampled to at most a number of points, and a reader for the binary
//! PLY files [`super::export`] writes.
//!
//! Coordinates are kept as they are (metres, the frame of the file: the scan's object frame), and
//! so are vertex colours (8-bit RGB), averaged over each cluster.

use std::collections::{HashMap, HashSet};

use super::mesh::TriangleMesh;

/// A model read from a PLY file: vertices (metres), optional colours, and faces (empty for a
/// point cloud).
pub type PlyModel = TriangleMesh;

/// Why a PLY file could not be read. `line` is the header line (1-based) the problem is on.
#[derive(Debug, thiserror::Error)]
pub enum PlyError {
    /// The header is missing, not binary little-endian, or has something this reader does not know.
    #[error("PLY header line {line}: {problem}")]
    Header {
        /// Header line, 1-based.
        line: usize,
        /// What is wrong.
        problem: String,
    },
    /// The body is shorter than the header announces.
    #[error("PLY body cut short: {element} {index} of {count} is missing")]
    Truncated {
        /// `vertex` or `face`.
        element: &'static str,
        /// The first missing item.
        index: usize,
        /// How many the header announced.
        count: usize,
    },
    /// A face is not a triangle or names a vertex that does not exist.
    #[error("PLY face {index}: {problem}")]
    Face {
        /// Face index.
        index: usize,
        /// What is wrong.
        problem: String,
    },
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Scalar {
    U8,
    I8,
    U16,
    I16,
    U32,
    I32,
    F32,
    F64,
}

impl Scalar {
    fn parse(s: &str) -> Option<Scalar> {
        Some(match s {
            "uchar" | "uint8" => Scalar::U8,
            "char" | "int8" => Scalar::I8,
            "ushort" | "uint16" => Scalar::U16,
            "short" | "int16" => Scalar::I16,
            "uint" | "uint32" => Scalar::U32,
            "int" | "int32" => Scalar::I32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }
    fn size(self) -> usize {
        match self {
            Scalar::U8 | Scalar::I8 => 1,
            Scalar::U16 | Scalar::I16 => 2,
            Scalar::U32 | Scalar::I32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }
    fn read(self, b: &[u8]) -> f64 {
        match self {
            Scalar::U8 => f64::from(b[0]),
            Scalar::I8 => f64::from(b[0] as i8),
            Scalar::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
            Scalar::I16 => f64::from(i16::from_le_bytes([b[0], b[1]])),
            Scalar::U32 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Scalar::I32 => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Scalar::F32 => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Scalar::F64 => f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]),
        }
    }
}

enum Property {
    Scalar(String, Scalar),
    List(String, Scalar, Scalar),
}

struct Element {
    name: String,
    count: usize,
    properties: Vec<Property>,
}

/// Read a binary little-endian PLY file: the `vertex` element's `x y z` (and `red green blue`
/// when present), the `face` element's `vertex_indices` (triangles only). Other elements and
/// properties are skipped.
pub fn read_ply(bytes: &[u8]) -> Result<PlyModel, PlyError> {
    let marker = b"end_header\n";
    let end = bytes
        .windows(marker.len())
        .position(|w| w == marker)
        .ok_or(PlyError::Header { line: 1, problem: "no `end_header` line".into() })?;
    let header = String::from_utf8_lossy(&bytes[..end]);
    let mut elements: Vec<Element> = Vec::new();
    for (n, line) in header.lines().enumerate() {
        let line_no = n + 1;
        let bad = |problem: String| PlyError::Header { line: line_no, problem };
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["ply"] if n == 0 => {}
            _ if n == 0 => return Err(bad("the file does not start with `ply`".into())),
            ["format", "binary_little_endian", _] => {}
            ["format", f, ..] => return Err(bad(format!("format {f} is not read (binary_little_endian only)"))),
            ["comment", ..] | ["obj_info", ..] | [] => {}
            ["element", name, count] => {
                let count = count.parse().map_err(|_| bad(format!("element count `{count}` is not a number")))?;
                elements.push(Element { name: (*name).to_owned(), count, properties: Vec::new() });
            }
            ["property", "list", c, t, name] => {
                let el = elements.last_mut().ok_or_else(|| bad("property before any element".into()))?;
                let c = Scalar::parse(c).ok_or_else(|| bad(format!("unknown type `{c}`")))?;
                let t = Scalar::parse(t).ok_or_else(|| bad(format!("unknown type `{t}`")))?;
                el.properties.push(Property::List((*name).to_owned(), c, t));
            }
            ["property", t, name] => {
                let el = elements.last_mut().ok_or_else(|| bad("property before any element".into()))?;
                let t = Scalar::parse(t).ok_or_else(|| bad(format!("unknown type `{t}`")))?;
                el.properties.push(Property::Scalar((*name).to_owned(), t));
            }
            _ => return Err(bad(format!("cannot read `{line}`"))),
        }
    }
    let mut body = &bytes[end + marker.len()..];
    let mut model = PlyModel::default();
    let mut colors: Vec<[u8; 3]> = Vec::new();
    for el in &elements {
        let element: &'static str = if el.name == "vertex" {
            "vertex"
        } else if el.name == "face" {
            "face"
        } else {
            "element"
        };
        if element == "vertex" {
            let has = |n: &str| el.properties.iter().any(|p| matches!(p, Property::Scalar(m, _) if m == n));
            if !(has("x") && has("y") && has("z")) {
                return Err(PlyError::Header { line: 0, problem: "the vertex element has no x, y and z".into() });
            }
        }
        let want_colour = element == "vertex"
            && ["red", "green", "blue"]
                .iter()
                .all(|c| el.properties.iter().any(|p| matches!(p, Property::Scalar(m, _) if m == c)));
        for index in 0..el.count {
            let count = el.count;
            let truncated = || PlyError::Truncated { element, index, count };
            let mut xyz = [0f32; 3];
            let mut rgb = [0u8; 3];
            for p in &el.properties {
                match p {
                    Property::Scalar(name, t) => {
                        let b = body.get(..t.size()).ok_or_else(truncated)?;
                        let v = t.read(b);
                        body = &body[t.size()..];
                        match name.as_str() {
                            "x" => xyz[0] = v as f32,
                            "y" => xyz[1] = v as f32,
                            "z" => xyz[2] = v as f32,
                            "red" => rgb[0] = v as u8,
                            "green" => rgb[1] = v as u8,
                            "blue" => rgb[2] = v as u8,
                            _ => {}
                        }
                    }
                    Property::List(name, c, t) => {
                        let b = body.get(..c.size()).ok_or_else(truncated)?;
                        let len = c.read(b) as usize;
                        body = &body[c.size()..];
                        let need = len * t.size();
                        let items = body.get(..need).ok_or_else(truncated)?;
                        if element == "face" && name == "vertex_indices" {
                            if len != 3 {
                                return Err(PlyError::Face { index, problem: format!("{len} vertices, not 3") });
                            }
                            let mut tri = [0u32; 3];
                            for (k, v) in tri.iter_mut().enumerate() {
                                let i = t.read(&items[k * t.size()..]);
                                if i < 0.0 || i as usize >= model.vertices.len() {
                                    return Err(PlyError::Face {
                                        index,
                                        problem: format!("vertex {i} of {}", model.vertices.len()),
                                    });
                                }
                                *v = i as u32;
                            }
                            model.triangles.push(tri);
                        }
                        body = &body[need..];
                    }
                }
            }
            if element == "vertex" {
                model.vertices.push(xyz);
                if want_colour {
                    colors.push(rgb);
                }
            }
        }
    }
    if !colors.is_empty() {
        model.colors = Some(colors);
    }
    Ok(model)
}

/// `mesh` decimated by vertex clustering to at most `max_faces` triangles: vertices are grouped
/// into cubic cells of a grid over the bounding box, each cell becomes one vertex at the mean of
/// its vertices (mean colour too), and triangles that collapse (two corners in one cell) or repeat
/// are dropped. The cell size starts at what `max_faces` suggests for a closed surface and grows
/// by a quarter until the result fits, so the result keeps the shape at the coarsest detail that
/// still fits. A mesh already within `max_faces` is returned as it is. Units and frame as in the
/// input (metres).
pub fn decimate_mesh(mesh: &TriangleMesh, max_faces: usize) -> TriangleMesh {
    if mesh.triangles.len() <= max_faces {
        return mesh.clone();
    }
    if max_faces == 0 || mesh.vertices.is_empty() {
        return TriangleMesh::default();
    }
    let (lo, hi) = bounds(&mesh.vertices);
    let extent = (0..3).map(|a| hi[a] - lo[a]).fold(0f32, f32::max).max(f32::MIN_POSITIVE);
    // A closed surface on an n^3 grid has about 4 n^2 faces... start at n = sqrt(max_faces / 2).
    let mut cells = ((max_faces as f64 / 2.0).sqrt().ceil() as u32).max(1);
    loop {
        let out = cluster(mesh, lo, extent / cells as f32);
        if out.triangles.len() <= max_faces || cells == 1 {
            if out.triangles.len() <= max_faces {
                return out;
            }
            return TriangleMesh::default();
        }
        cells = ((cells as f32 * 0.8) as u32).min(cells - 1).max(1);
    }
}

fn bounds(points: &[[f32; 3]]) -> ([f32; 3], [f32; 3]) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for p in points {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    (lo, hi)
}

/// One vertex per occupied cell of size `cell` (metres) from `lo`.
fn cluster(mesh: &TriangleMesh, lo: [f32; 3], cell: f32) -> TriangleMesh {
    let mut index: HashMap<[i32; 3], u32> = HashMap::new();
    let mut sums: Vec<([f64; 3], [u32; 3], u32)> = Vec::new();
    let colors = mesh.colors.as_ref().filter(|c| c.len() == mesh.vertices.len());
    let remap: Vec<u32> = mesh
        .vertices
        .iter()
        .enumerate()
        .map(|(n, p)| {
            let key = [0, 1, 2].map(|a| ((p[a] - lo[a]) / cell).floor() as i32);
            let k = *index.entry(key).or_insert_with(|| {
                sums.push(([0.0; 3], [0; 3], 0));
                (sums.len() - 1) as u32
            });
            let s = &mut sums[k as usize];
            for a in 0..3 {
                s.0[a] += f64::from(p[a]);
            }
            if let Some(c) = colors {
                for a in 0..3 {
                    s.1[a] += u32::from(c[n][a]);
                }
            }
            s.2 += 1;
            k
        })
        .collect();
    let mut seen: HashSet<[u32; 3]> = HashSet::new();
    let mut triangles = Vec::new();
    for t in &mesh.triangles {
        let r = t.map(|i| remap[i as usize]);
        if r[0] == r[1] || r[1] == r[2] || r[0] == r[2] {
            continue;
        }
        let mut key = r;
        key.sort_unstable();
        if seen.insert(key) {
            triangles.push(r);
        }
    }
    let vertices = sums.iter().map(|(s, _, n)| s.map(|v| (v / f64::from(*n)) as f32)).collect();
    let colors = colors.map(|_| sums.iter().map(|(_, c, n)| c.map(|v| (v / n) as u8)).collect());
    let mut out = TriangleMesh { vertices, triangles, colors };
    drop_unused(&mut out);
    out
}

/// Remove vertices no triangle uses (renumbering the triangles).
fn drop_unused(mesh: &mut TriangleMesh) {
    let mut used = vec![u32::MAX; mesh.vertices.len()];
    let mut next = 0u32;
    for t in &mut mesh.triangles {
        for i in t.iter_mut() {
            if used[*i as usize] == u32::MAX {
                used[*i as usize] = next;
                next += 1;
            }
            *i = used[*i as usize];
        }
    }
    let mut vertices = vec![[0f32; 3]; next as usize];
    let mut colors = mesh.colors.as_ref().map(|_| vec![[0u8; 3]; next as usize]);
    for (old, &new) in used.iter().enumerate() {
        if new != u32::MAX {
            vertices[new as usize] = mesh.vertices[old];
            if let (Some(out), Some(c)) = (colors.as_mut(), mesh.colors.as_ref()) {
                out[new as usize] = c[old];
            }
        }
    }
    mesh.vertices = vertices;
    mesh.colors = colors;
}

/// At most `max_points` of `points` (and their colours), evenly spread through the list: every
/// k-th point for the smallest k that fits. Units as in the input (metres).
pub fn subsample_points(
    points: &[[f32; 3]],
    colors: Option<&Vec<[u8; 3]>>,
    max_points: usize,
) -> (Vec<[f32; 3]>, Option<Vec<[u8; 3]>>) {
    let colors = colors.filter(|c| c.len() == points.len());
    if points.len() <= max_points {
        return (points.to_vec(), colors.cloned());
    }
    if max_points == 0 {
        return (Vec::new(), colors.map(|_| Vec::new()));
    }
    let step = points.len().div_ceil(max_points);
    let p = points.iter().step_by(step).copied().collect();
    let c = colors.map(|c| c.iter().step_by(step).copied().collect());
    (p, c)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::export::{ply_mesh_bytes, ply_points_bytes};

    /// A UV sphere of radius `r` metres with `n` rings and `2n` segments, coloured by height.
    fn sphere(r: f32, n: u32) -> TriangleMesh {
        let mut vertices = vec![[0.0, 0.0, r], [0.0, 0.0, -r]];
        let seg = 2 * n;
        for i in 1..n {
            let th = std::f32::consts::PI * i as f32 / n as f32;
            for j in 0..seg {
                let ph = 2.0 * std::f32::consts::PI * j as f32 / seg as f32;
                vertices.push([r * th.sin() * ph.cos(), r * th.sin() * ph.sin(), r * th.cos()]);
            }
        }
        let at = |i: u32, j: u32| 2 + (i - 1) * seg + j % seg;
        let mut triangles = Vec::new();
        for j in 0..seg {
            triangles.push([0, at(1, j), at(1, j + 1)]);
            triangles.push([1, at(n - 1, j + 1), at(n - 1, j)]);
            for i in 1..n - 1 {
                triangles.push([at(i, j), at(i + 1, j), at(i + 1, j + 1)]);
                triangles.push([at(i, j), at(i + 1, j + 1), at(i, j + 1)]);
            }
        }
        let colors = vertices.iter().map(|v| [((v[2] / r + 1.0) * 127.0) as u8, 10, 200]).collect();
        TriangleMesh { vertices, triangles, colors: Some(colors) }
    }

    #[test]
    fn decimation_fits_the_budget_and_keeps_the_shape() {
        let m = sphere(0.05, 60);
        assert!(m.triangles.len() > 10_000);
        let volume = m.signed_volume();
        for budget in [5000, 1000, 300] {
            let d = decimate_mesh(&m, budget);
            assert!(d.triangles.len() <= budget, "{} > {budget}", d.triangles.len());
            assert!(d.triangles.len() > budget / 8, "{} faces for a budget of {budget}", d.triangles.len());
            // Every vertex stays near the sphere (within a cell), the volume within 15 %.
            let worst = d.vertices.iter().map(|v| ((v[0].powi(2) + v[1].powi(2) + v[2].powi(2)).sqrt() - 0.05).abs());
            assert!(worst.fold(0f32, f32::max) < 0.01);
            let rel = (d.signed_volume() - volume).abs() / volume;
            assert!(rel < 0.15, "volume off by {rel} at {budget} faces");
            let c = d.colors.as_ref().expect("colours kept");
            assert_eq!(c.len(), d.vertices.len());
            // Colour follows height: the top vertex is red-ish, the bottom one not.
            let top = (0..d.vertices.len()).max_by(|&a, &b| d.vertices[a][2].total_cmp(&d.vertices[b][2]));
            assert!(c[top.expect("vertex")][0] > 200);
            assert!(d.triangles.iter().flatten().all(|&i| (i as usize) < d.vertices.len()));
        }
        assert_eq!(decimate_mesh(&m, m.triangles.len()), m);
        assert!(decimate_mesh(&m, 0).triangles.is_empty());
    }

    #[test]
    fn subsampling_fits_and_spreads() {
        let pts: Vec<[f32; 3]> = (0..1000).map(|i| [i as f32, 0.0, 0.0]).collect();
        let cols: Vec<[u8; 3]> = (0..1000).map(|i| [(i % 256) as u8, 0, 0]).collect();
        let (p, c) = subsample_points(&pts, Some(&cols), 300);
        assert!(p.len() <= 300 && p.len() >= 250, "{}", p.len());
        assert_eq!(c.expect("colours").len(), p.len());
        assert!(p.last().expect("point")[0] > 900.0, "spread to the end of the list");
        assert_eq!(subsample_points(&pts, None, 5000).0.len(), 1000);
    }

    #[test]
    fn the_writers_output_reads_back() {
        let m = sphere(0.02, 8);
        let back = read_ply(&ply_mesh_bytes(&m)).expect("read");
        assert_eq!(back, m);
        let pts = vec![[0.1, 0.2, 0.3], [-1.0, 2.0, 3.5]];
        let back = read_ply(&ply_points_bytes(&pts, None)).expect("read");
        assert_eq!(back.vertices, pts);
        assert!(back.triangles.is_empty() && back.colors.is_none());
    }

    #[test]
    fn bad_files_name_the_problem() {
        let e = read_ply(b"ply\nformat ascii 1.0\nend_header\n").expect_err("ascii");
        assert!(e.to_string().contains("line 2"), "{e}");
        let mut cut = ply_points_bytes(&[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], None);
        cut.truncate(cut.len() - 5);
        let e = read_ply(&cut).expect_err("truncated");
        assert!(e.to_string().contains("vertex 1 of 2"), "{e}");
        let bad = b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar uint vertex_indices\nend_header\n\x03\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00";
        let e = read_ply(bad).expect_err("bad index");
        assert!(e.to_string().contains("face 0"), "{e}");
    }
}

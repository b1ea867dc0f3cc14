//! End-to-end: every scan's mesh is one closed, consistently oriented component without cavities
//! and without handles (the simulated cup has none: Euler characteristic 2), simplified by default
//! within the stated error bound (`[reconstruction.mesh] max_error_voxels`, a quarter voxel unless
//! the rig says otherwise), as its report says; checked on the model.ply the scan wrote, not only on
//! the report.

mod scan_common;

use scan_common::{derived_rig, run_scan};

/// Components, open or misoriented directed edges, and Euler characteristic of a binary PLY mesh as
/// scanrig writes it (float x y z, optional uchar colours, uchar-counted uint faces).
fn ply_topology(path: &std::path::Path) -> (usize, usize, usize, i64) {
    let bytes = std::fs::read(path).expect("model.ply readable");
    let end = bytes.windows(11).position(|w| w == b"end_header\n").expect("PLY header") + 11;
    let header = String::from_utf8_lossy(&bytes[..end]).to_string();
    let count = |element: &str| -> usize {
        header
            .lines()
            .find_map(|l| l.strip_prefix(&format!("element {element} ")))
            .and_then(|n| n.trim().parse().ok())
            .unwrap_or_else(|| panic!("no element {element} in {header}"))
    };
    let (nv, nf) = (count("vertex"), count("face"));
    let stride = 12 + if header.contains("property uchar red") { 3 } else { 0 };
    let faces = &bytes[end + nv * stride..];
    assert_eq!(faces.len(), nf * 13, "{header}");
    let tris: Vec<[u32; 3]> = faces
        .chunks_exact(13)
        .map(|f| {
            assert_eq!(f[0], 3);
            [0, 1, 2].map(|k| u32::from_le_bytes([f[1 + 4 * k], f[2 + 4 * k], f[3 + 4 * k], f[4 + 4 * k]]))
        })
        .collect();
    let mut directed = std::collections::HashMap::new();
    let mut parent: Vec<usize> = (0..nv).collect();
    fn find(p: &mut [usize], mut x: usize) -> usize {
        while p[x] != x {
            p[x] = p[p[x]];
            x = p[x];
        }
        x
    }
    for t in &tris {
        for e in 0..3 {
            *directed.entry((t[e], t[(e + 1) % 3])).or_insert(0u32) += 1;
            let (a, b) = (find(&mut parent, t[e] as usize), find(&mut parent, t[(e + 1) % 3] as usize));
            parent[a] = b;
        }
    }
    let open = directed.iter().filter(|(&(a, b), &n)| n != 1 || directed.get(&(b, a)) != Some(&1)).count();
    let mut roots: Vec<usize> = tris.iter().map(|t| find(&mut parent, t[0] as usize)).collect();
    roots.sort_unstable();
    roots.dedup();
    let mut used: Vec<u32> = tris.iter().flatten().copied().collect();
    used.sort_unstable();
    used.dedup();
    let euler = used.len() as i64 - (directed.len() / 2) as i64 + tris.len() as i64;
    (tris.len(), roots.len(), open, euler)
}

#[test]
fn every_methods_mesh_is_one_closed_simplified_component() {
    for (base, replace) in [
        // Space carving: the relaxed visual hull of the cup.
        (
            "config/rigs/simulated.toml",
            vec![("resolution = 128", "resolution = 64"), ("positions = 24", "positions = 12")],
        ),
        // Voxel colouring: hundreds of floating blobs and cavities before the clean-up.
        (
            "config/rigs/voxel-coloring.toml",
            vec![("resolution = 128", "resolution = 48"), ("positions = 36", "positions = 12")],
        ),
        // Structured light (phase shift): TSDF surface with floating blobs, and voxel-scale tunnels
        // (Euler characteristic -24 without their removal).
        (
            "config/rigs/structured-light-phase.toml",
            vec![("resolution = 128", "resolution = 64"), ("positions = 16", "positions = 6")],
        ),
        // Laser: the cloud's solid has voxel-scale tunnels and bridges (Euler characteristic -126
        // without their removal).
        ("config/rigs/laser.toml", vec![("positions = 180", "positions = 60")]),
        // Generalized space carving: photo-consistency leaves voxel-scale tunnels (-62 without their
        // removal).
        (
            "config/rigs/space-carving-photo.toml",
            vec![("resolution = 128", "resolution = 64"), ("positions = 36", "positions = 12")],
        ),
    ] {
        let dir = tempfile::tempdir().expect("tempdir");
        let rig = derived_rig(dir.path(), base, &replace);
        let out = dir.path().join("out");
        let report = run_scan(&rig, &out);
        let topo = &report["mesh_topology"];
        assert_eq!(topo["components"], 1, "{base}: {topo}");
        assert_eq!(topo["cavities"], 0, "{base}: {topo}");
        assert_eq!(topo["open_or_misoriented_edges"], 0, "{base}: {topo}");
        // No handle: the voxel-scale ones were removed before meshing, within a voxel of the surface.
        assert_eq!(topo["euler_characteristic"], 2, "{base}: {topo}, handles removed: {}", report["mesh_handles"]);
        let handles = &report["mesh_handles"];
        assert!(handles["seconds"].as_f64().is_some(), "{base}: {handles}");
        // The rigs do not ask for a simplification: this is the default.
        let s = &report["mesh_simplification"];
        assert_eq!(s["within_bound"], true, "{base}: {s}");
        let voxel = report["voxel_size_m"].as_f64().expect("voxel size");
        let bound = s["max_error_m"].as_f64().expect("bound");
        assert!((bound - 0.25 * voxel).abs() < 1e-12, "{base}: the bound asked for is a quarter voxel: {s}");
        let hausdorff = s["hausdorff"]["symmetric_m"].as_f64().expect("hausdorff");
        assert!(hausdorff <= bound, "{base}: Hausdorff {hausdorff} above the bound {bound}");
        let (before, after) = (s["triangles_before"].as_u64().expect("n"), s["triangles_after"].as_u64().expect("n"));
        assert!(after * 2 < before, "{base}: {before} -> {after} triangles");
        assert_eq!(report["mesh_triangles"].as_u64(), Some(after), "{base}");
        let (triangles, components, open, euler) = ply_topology(&out.join("model.ply"));
        assert_eq!((triangles as u64, components, open), (after, 1, 0), "{base}: model.ply");
        assert_eq!(Some(euler), topo["euler_characteristic"].as_i64(), "{base}: model.ply");
    }
}

/// `max_error_voxels = 0` turns the simplification off; the clean-up still runs.
#[test]
fn simplification_is_off_with_a_zero_bound() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = derived_rig(
        dir.path(),
        "config/rigs/simulated.toml",
        &[
            ("resolution = 128", "resolution = 40\n\n[reconstruction.mesh]\nmax_error_voxels = 0"),
            ("positions = 24", "positions = 8"),
        ],
    );
    let report = run_scan(&rig, &dir.path().join("out"));
    assert!(report.get("mesh_simplification").is_none(), "{}", report["mesh_simplification"]);
    assert_eq!(report["mesh_topology"]["components"], 1);
    assert_eq!(report["mesh_topology"]["triangles"], report["mesh_triangles"]);
}

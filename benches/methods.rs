//! Every other method against its peer or target, in one run: TSDF depth fusion against Open3D's
//! `UniformTSDFVolume.integrate` (`benches/tsdf_open3d_peer.py`, same 16-bit millimetre depth maps,
//! intrinsics, poses, voxel size and truncation), laser stripe extraction + triangulation at
//! 640x480 and 1280x960 against a numpy implementation of the same per-row peak
//! (`benches/laser_numpy_peer.py`, same PNG frames), structured light decode + triangulate + merge
//! of one 1280x1024 view (Gray code, 4-step phase shift; merge: the valid points with their normals
//! and colours gathered into a cloud, as a scan does per view), and shadow carving at 128³ with 24
//! positions x 4 lights of a bowl whose pit only shadows can carve, against the implementation it
//! replaced (`benches/shadow_baseline.rs`, same result checked). Inputs are synthetic and analytic
//! (a sphere, a plane, a bowl); the peers read the
//! files this bench writes to a temporary directory, and are run by it, so each ratio comes from
//! one run: ours and the peer alternate in three rounds, and the ratio stated is the median of the
//! three rounds' ratios (a change in the machine's load then sways one round, not the ratio). Each
//! case prints a line and a `PERF` line (JSON) for `benches/perf_table.py`; a peer that cannot run
//! (no python3, no Open3D) is reported as such, with no ratio.
//!
//! `cargo bench --bench methods [-- tsdf laser structured-light shadow]`; `PYTHON=...` picks the
//! interpreter.

use std::hint::black_box;
use std::path::Path;
use std::process::Command;
use std::time::Instant;

use image::{ImageBuffer, Luma, RgbImage};
use rayon::prelude::*;
use scanrig::geometry::{Aabb, CameraModel, Intrinsics, Pose, Vector3, VoxelGrid};
use scanrig::pipeline::laser::{detect_stripe, triangulate_peaks, Plane, StripeParams};
use scanrig::pipeline::structured_light::phase::{PhaseDecodeParams, PhaseShiftPatterns, Unwrapping};
use scanrig::pipeline::structured_light::{
    decode, DecodeParams, GrayCodePatterns, ProjectorMap, RangeImage, TriangulationParams, Triangulator,
};
use scanrig::pipeline::{
    carve_shadows, extract_surface, hausdorff_distance, simplify, simplify_in, FusionParams, Mask, MeshParams,
    Occupancy, PointCloud, ShadowCarveParams, ShadowCarver, ShadowView, SimplifyParams, Tsdf,
};

#[path = "shadow_baseline.rs"]
mod shadow_baseline;

/// Median wall-clock seconds of `runs` calls.
fn median_s(runs: usize, mut f: impl FnMut()) -> f64 {
    let mut t: Vec<f64> = (0..runs)
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64()
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[runs / 2]
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// One line for `benches/perf_table.py`. `ours` and the peer's seconds in seconds per unit of work,
/// with the ratio (theirs / ours) to state; `rate` the unit's name when the figure is a throughput
/// (frames/s, clouds/s).
fn perf_line(method: &str, case: &str, ours: f64, peer: Option<(&str, f64, f64)>, rate: Option<&str>) {
    let (name, p, ratio) = peer.map_or((None, None, None), |(n, s, r)| (Some(n), Some(s), Some(r)));
    println!(
        "PERF {}",
        serde_json::json!({"method": method, "case": case, "ours_s": ours, "peer": name, "peer_s": p,
            "ratio": ratio, "rate": rate})
    );
}

/// Rounds of ours against a peer script, alternated.
const ROUNDS: usize = 3;

/// Ours (`median_s(runs, f)`) and the peer script (`run_peer`) alternately, [`ROUNDS`] times: a
/// change in the machine's load between the two sides then shows in one round instead of biasing
/// the ratio. Returns the median of our times and, unless the peer failed, the median of its times
/// and of the per-round ratios.
fn paired(runs: usize, script: &str, args: &[&str], mut f: impl FnMut()) -> (f64, Result<(f64, f64), String>) {
    let (mut ours, mut theirs, mut ratios) = (Vec::new(), Vec::new(), Vec::new());
    let mut failed = None;
    for _ in 0..ROUNDS {
        let o = median_s(runs, &mut f);
        ours.push(o);
        if failed.is_none() {
            match run_peer(script, args) {
                Ok(p) => {
                    theirs.push(p);
                    ratios.push(p / o);
                }
                Err(e) => failed = Some(e),
            }
        }
    }
    let peer = match failed {
        Some(e) => Err(e),
        None => Ok((median(theirs), median(ratios))),
    };
    (median(ours), peer)
}

/// Run `benches/<script>` with `args`; its last line `PEER_S <seconds>` is the peer's time.
fn run_peer(script: &str, args: &[&str]) -> Result<f64, String> {
    let python = std::env::var("PYTHON").unwrap_or_else(|_| "python3".into());
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches").join(script);
    let out = Command::new(&python).arg(&path).args(args).output().map_err(|e| format!("{python}: {e}"))?;
    let text = String::from_utf8_lossy(&out.stdout);
    print!("{text}");
    if !out.status.success() {
        return Err(String::from_utf8_lossy(&out.stderr).lines().last().unwrap_or("failed").to_string());
    }
    text.lines()
        .rev()
        .find_map(|l| l.strip_prefix("PEER_S ").and_then(|x| x.trim().parse().ok()))
        .ok_or_else(|| "no PEER_S line".into())
}

fn intrinsics(w: u32, h: u32, f: f64) -> Intrinsics {
    Intrinsics { fx: f, fy: f, cx: w as f64 / 2.0, cy: h as f64 / 2.0, ..Intrinsics::default() }
}

/// Distance along the unit ray `o + t d` to the sphere (centre `c`, radius `r`), if it hits.
fn hit_sphere(o: &Vector3<f64>, d: &Vector3<f64>, c: &Vector3<f64>, r: f64) -> Option<f64> {
    let oc = o - c;
    let b = oc.dot(d);
    let disc = b * b - (oc.norm_squared() - r * r);
    (disc >= 0.0).then(|| -b - disc.sqrt()).filter(|&t| t > 0.0)
}

fn ring(n: usize, radius: f64, height: f64, w: u32, h: u32, f: f64) -> Vec<CameraModel> {
    (0..n)
        .map(|i| {
            let a = i as f64 / n as f64 * std::f64::consts::TAU;
            let eye = Vector3::new(radius * a.cos(), radius * a.sin(), height);
            CameraModel {
                width: w,
                height: h,
                intrinsics: intrinsics(w, h, f),
                pose: Pose::look_at(eye, Vector3::zeros(), Vector3::z()),
            }
        })
        .collect()
}

fn tsdf(dir: &Path) {
    const R: f64 = 0.05;
    let (w, h) = (640u32, 480u32);
    let cams = ring(24, 0.35, 0.12, w, h, 525.0);
    let centre = Vector3::zeros();
    let n = 128u32;
    let bbox = Aabb { min: [-0.07; 3], max: [0.07; 3] };
    let grid = VoxelGrid::from_resolution(&bbox, n);
    let trunc = 3.0 * grid.voxel_size;
    // Depth maps in whole millimetres, as the PNGs hold them, so both sides fuse the same values.
    let mut depths = Vec::new();
    let mut meta = Vec::new();
    for (i, cam) in cams.iter().enumerate() {
        let o = cam.centre();
        let mut png: ImageBuffer<Luma<u16>, Vec<u16>> = ImageBuffer::new(w, h);
        let mut depth = vec![0f32; (w * h) as usize];
        for v in 0..h {
            for u in 0..w {
                let d = cam.pixel_ray(u as f64 + 0.5, v as f64 + 0.5).normalize();
                if let Some(t) = hit_sphere(&o, &d, &centre, R) {
                    let z = cam.pose.apply(&(o + d * t)).z;
                    let mm = (z * 1000.0).round() as u16;
                    png.put_pixel(u, v, Luma([mm]));
                    depth[(v * w + u) as usize] = mm as f32 / 1000.0;
                }
            }
        }
        png.save(dir.join(format!("depth_{i:02}.png"))).expect("write depth PNG");
        depths.push(depth);
        let r = &cam.pose.rotation;
        let t = &cam.pose.translation;
        let ext: Vec<Vec<f64>> = (0..4)
            .map(|a| if a < 3 { vec![r[(a, 0)], r[(a, 1)], r[(a, 2)], t[a]] } else { vec![0.0, 0.0, 0.0, 1.0] })
            .collect();
        meta.push(serde_json::json!({"depth": format!("depth_{i:02}.png"), "extrinsic": ext}));
    }
    let i = cams[0].intrinsics;
    let spec = serde_json::json!({"width": w, "height": h, "fx": i.fx, "fy": i.fy, "cx": i.cx, "cy": i.cy,
        "origin": bbox.min, "length": bbox.max[0] - bbox.min[0], "resolution": n, "sdf_trunc": trunc,
        "views": meta});
    let spec_path = dir.join("tsdf.json");
    std::fs::write(&spec_path, spec.to_string()).expect("write tsdf.json");
    let params = FusionParams { truncation_m: trunc, max_weight: 64.0, missing_is_free: true };
    let (ours, peer) = paired(5, "tsdf_open3d_peer.py", &[spec_path.to_str().expect("utf-8 path")], || {
        let mut t = Tsdf::new(grid, params).expect("grid");
        for (cam, d) in cams.iter().zip(&depths) {
            t.integrate(cam, d).expect("integrates");
        }
        black_box(t);
    });
    println!("tsdf {n}^3, 24 depth maps 640x480: {:.3} s ({:.1} ms per map)", ours, ours / 24.0 * 1e3);
    // Free-space samples given to whole bricks stay pending until a voxel is read; reading the solid
    // out folds them in. Timed apart (neither side's fusion time above includes a read-out).
    let mut fused = Tsdf::new(grid, params).expect("grid");
    for (cam, d) in cams.iter().zip(&depths) {
        fused.integrate(cam, d).expect("integrates");
    }
    let readout = median_s(5, || {
        black_box(fused.occupancy());
    });
    println!("tsdf read-out of the fused solid (Tsdf::occupancy): {:.3} s", readout);
    let (stored, bricks) = fused.stored_bricks();
    println!(
        "tsdf storage: {stored} of {bricks} bricks hold voxels, {:.1} MB (dense value and weight: {:.1} MB)",
        fused.memory_bytes() as f64 / 1e6,
        (grid.len() * 8) as f64 / 1e6
    );
    match peer {
        Ok((p, ratio)) => {
            println!(
                "tsdf: Open3D UniformTSDFVolume {p:.3} s, ratio {ratio:.1}x (median of {ROUNDS} alternated rounds)"
            );
            perf_line(
                "depth-fusion (TSDF)",
                "128^3, 24 depth maps 640x480",
                ours,
                Some(("Open3D UniformTSDFVolume", p, ratio)),
                None,
            );
        }
        Err(e) => {
            println!("tsdf: peer unavailable ({e})");
            perf_line("depth-fusion (TSDF)", "128^3, 24 depth maps 640x480", ours, None, None);
        }
    }
}

fn laser(dir: &Path) {
    for (w, h) in [(640u32, 480u32), (1280, 960)] {
        let f = 1.3 * w as f64;
        let cam = CameraModel {
            width: w,
            height: h,
            intrinsics: intrinsics(w, h, f),
            pose: Pose::look_at(Vector3::new(0.0, -0.3, 0.1), Vector3::zeros(), Vector3::z()),
        };
        let plane = Plane::through([0.0, 0.0, 0.0], [1.0, 0.2, 0.0]).expect("plane");
        // A dark scene with texture, and the same with a red stripe that wanders across the rows.
        let off = RgbImage::from_fn(w, h, |u, v| {
            let g = (20 + (u * 7 + v * 13) % 23) as u8;
            image::Rgb([g, g, g])
        });
        let on = RgbImage::from_fn(w, h, |u, v| {
            let c = w as f64 / 2.0 + (v as f64 * 0.013).sin() * w as f64 / 6.0;
            let s = 200.0 * (-((u as f64 - c) / 1.5).powi(2)).exp();
            let p = off.get_pixel(u, v).0;
            image::Rgb([(p[0] as f64 + s).min(255.0) as u8, p[1], p[2]])
        });
        let (off_path, on_path) = (dir.join(format!("laser_off_{w}.png")), dir.join(format!("laser_on_{w}.png")));
        off.save(&off_path).expect("write");
        on.save(&on_path).expect("write");
        let params = StripeParams::default();
        let frame = || {
            let peaks = detect_stripe(&off, &on, [255, 0, 0], &params).expect("params");
            triangulate_peaks(&cam, &plane, &peaks)
        };
        // Once untimed: the peer checks its point count against ours.
        let points = frame().len();
        let spec = serde_json::json!({"off": off_path, "on": on_path, "min_peak": params.min_peak,
            "max_width": params.max_width_px, "half_window": params.half_window_px,
            "fx": f, "fy": f, "cx": w as f64 / 2.0, "cy": h as f64 / 2.0,
            "rotation": (0..3).map(|a| (0..3).map(|b| cam.pose.rotation[(a, b)]).collect::<Vec<_>>()).collect::<Vec<_>>(),
            "translation": [cam.pose.translation.x, cam.pose.translation.y, cam.pose.translation.z],
            "plane_normal": plane.normal, "plane_offset": plane.offset_m, "points": points});
        let spec_path = dir.join(format!("laser_{w}.json"));
        std::fs::write(&spec_path, spec.to_string()).expect("write");
        let (ours, peer) = paired(51, "laser_numpy_peer.py", &[spec_path.to_str().expect("utf-8 path")], || {
            black_box(frame());
        });
        let case = format!("{w}x{h}, one stripe");
        println!("laser {w}x{h}: {:.3} ms per frame ({:.0} frames/s), {points} points", ours * 1e3, 1.0 / ours);
        match peer {
            Ok((p, ratio)) => {
                println!(
                    "laser {w}x{h}: numpy {:.3} ms per frame, ratio {ratio:.1}x (median of {ROUNDS} alternated rounds)",
                    p * 1e3
                );
                perf_line("laser", &case, ours, Some(("numpy per-row peak", p, ratio)), Some("frames/s"));
            }
            Err(e) => {
                println!("laser: peer unavailable ({e})");
                perf_line("laser", &case, ours, None, Some("frames/s"));
            }
        }
    }
}

/// Camera and projector side by side looking at a plane 0.5 m away; the capture of `pattern`
/// (projector-sized grey images) as the camera sees it.
fn procam(w: u32, h: u32) -> (CameraModel, CameraModel) {
    let target = Vector3::new(0.0, 0.0, 0.0);
    let cam = CameraModel {
        width: w,
        height: h,
        intrinsics: intrinsics(w, h, 1.2 * w as f64),
        pose: Pose::look_at(Vector3::new(-0.1, -0.5, 0.0), target, Vector3::z()),
    };
    let proj = CameraModel {
        width: 1024,
        height: 768,
        intrinsics: intrinsics(1024, 768, 1000.0),
        pose: Pose::look_at(Vector3::new(0.1, -0.5, 0.0), target, Vector3::z()),
    };
    (cam, proj)
}

/// Per camera pixel, the projector pixel that lights it (the scene is the plane y = 0, facing
/// both), or `None`.
fn lookup(cam: &CameraModel, proj: &CameraModel) -> Vec<Option<usize>> {
    let o = cam.centre();
    (0..cam.height)
        .flat_map(|v| (0..cam.width).map(move |u| (u, v)))
        .map(|(u, v)| {
            let d = cam.pixel_ray(u as f64 + 0.5, v as f64 + 0.5);
            let t = -o.y / d.y;
            if t <= 0.0 {
                return None;
            }
            let (pu, pv) = proj.pixel_of(&(o + d * t))?;
            Some((pv * proj.width + pu) as usize)
        })
        .collect()
}

/// CPU seconds this process has used so far (user + system, every thread), from `/proc/self/stat`
/// in clock ticks (10 ms, so only sums over many runs mean much); 0 where unavailable. Unlike wall
/// time it does not grow while other processes hold the cores.
fn cpu_s() -> f64 {
    let ticks = |s: String| -> Option<f64> {
        let f: Vec<&str> = s.rsplit_once(')')?.1.split_whitespace().collect();
        Some(f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?)
    };
    std::fs::read_to_string("/proc/self/stat").ok().and_then(ticks).map_or(0.0, |t| t / 100.0)
}

/// Per-run wall and CPU times of the structured-light stages (decode, triangulation, merge):
/// medians of the wall times and mean CPU time per view.
#[derive(Default)]
struct Stages {
    wall: Vec<[f64; 3]>,
    cpu: [f64; 3],
    /// Wall seconds of the triangulator's passes, per run.
    passes: Vec<[f64; 4]>,
    last: (Option<Instant>, f64),
}

impl Stages {
    fn start(&mut self) {
        self.last = (Some(Instant::now()), cpu_s());
    }

    /// Ends stage `k` and starts the next.
    fn lap(&mut self, k: usize) {
        let (now, cpu) = (Instant::now(), cpu_s());
        if k == 0 {
            self.wall.push([0.0; 3]);
        }
        if let (Some(t), Some(w)) = (self.last.0, self.wall.last_mut()) {
            w[k] = (now - t).as_secs_f64();
        }
        self.cpu[k] += cpu - self.last.1;
        self.last = (Some(now), cpu);
    }

    fn print(&self, coding: &str) {
        let median = |k: usize| {
            let mut v: Vec<f64> = self.wall.iter().map(|s| s[k]).collect();
            v.sort_by(f64::total_cmp);
            v.get(v.len() / 2).copied().unwrap_or(0.0) * 1e3
        };
        let cpu = |k: usize| self.cpu[k] / self.wall.len().max(1) as f64 * 1e3;
        let pass = |k: usize| {
            let mut v: Vec<f64> = self.passes.iter().map(|s| s[k]).collect();
            v.sort_by(f64::total_cmp);
            v.get(v.len() / 2).copied().unwrap_or(0.0) * 1e3
        };
        println!(
            "structured light {coding} stages, wall median (CPU mean, all threads) per view: decode {:.1} ms ({:.0}), \
             triangulate + neighbour test + normals + colours {:.1} ms ({:.0}), merge {:.1} ms ({:.0})",
            median(0),
            cpu(0),
            median(1),
            cpu(1),
            median(2),
            cpu(2)
        );
        println!(
            "structured light {coding} triangulator passes, wall median: points {:.1} ms, neighbour test {:.1} ms, \
             normals + colours {:.1} ms, clearing outliers {:.1} ms",
            pass(0),
            pass(1),
            pass(2),
            pass(3)
        );
    }
}

fn structured_light() {
    let (w, h) = (1280u32, 1024u32);
    let (cam, proj) = procam(w, h);
    let map = lookup(&cam, &proj);
    let capture = |pattern: &[u8]| -> Vec<u8> {
        map.iter().map(|m| m.map_or(10, |i| (30 + u32::from(pattern[i]) * 180 / 255) as u8)).collect()
    };
    let tri = TriangulationParams::default();
    // The camera's rays are computed once per camera and projector pair, outside the timing; the
    // range image's buffers are reused from view to view, as a scan does.
    let mut triangulator = Triangulator::new(&cam, &proj).expect("models");
    let mut range = RangeImage::default();
    // Gray code.
    let gray = GrayCodePatterns::new(proj.width, proj.height).expect("projector");
    let images: Vec<Vec<u8>> = (0..gray.count()).map(|i| capture(&gray.render(i).expect("in range"))).collect();
    let imgs: Vec<&[u8]> = images.iter().map(Vec::as_slice).collect();
    let prm = DecodeParams::default();
    let mut pm = ProjectorMap::new();
    let mut merged = PointCloud::new();
    let mut stages = Stages::default();
    let mut gray_view = |stages: &mut Stages| {
        stages.start();
        decode(&gray, &imgs, w as usize, h as usize, &prm, &mut pm).expect("decodes");
        stages.lap(0);
        triangulator.triangulate_map_into(&pm, true, None, &tri, &mut range).expect("triangulates");
        stages.lap(1);
        stages.passes.push(triangulator.last_pass_seconds());
        let cloud = range.valid_cloud();
        let points = cloud.len();
        merged = PointCloud::new();
        merged.extend(cloud);
        stages.lap(2);
        points
    };
    // Once untimed: the peer checks its point count against ours.
    let points = gray_view(&mut Stages::default());
    // The peer decodes OpenCV's own Gray-code images, synthesised through the same camera ->
    // projector lookup, and triangulates with the same calibration.
    let dir = tempfile::tempdir().expect("temporary directory");
    let lookup_path = dir.path().join("sl_lookup.i32");
    let raw: Vec<u8> = map.iter().flat_map(|m| m.map_or(-1i32, |i| i as i32).to_le_bytes()).collect();
    std::fs::write(&lookup_path, raw).expect("write");
    let model = |m: &CameraModel| {
        let k = &m.intrinsics;
        let r = &m.pose.rotation;
        let t = &m.pose.translation;
        serde_json::json!({"width": m.width, "height": m.height, "fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy,
            "rotation": (0..3).map(|i| [r[(i, 0)], r[(i, 1)], r[(i, 2)]]).collect::<Vec<_>>(),
            "translation": [t.x, t.y, t.z]})
    };
    let spec = serde_json::json!({"camera": model(&cam), "projector": model(&proj),
        "lookup": lookup_path.to_str().expect("utf-8 path"), "points": points});
    let spec_path = dir.path().join("sl.json");
    std::fs::write(&spec_path, spec.to_string()).expect("write");
    let (ours, peer) = paired(7, "opencv_sl_peer.py", &[spec_path.to_str().expect("utf-8 path")], || {
        black_box(gray_view(&mut stages));
    });
    stages.print("Gray code");
    println!(
        "structured light Gray code {w}x{h} ({} images): decode + triangulate + merge {:.1} ms ({:.1} clouds/s), {points} points",
        gray.count(),
        ours * 1e3,
        1.0 / ours
    );
    match peer {
        Ok((p, ratio)) => {
            println!(
                "structured light Gray code: OpenCV {:.1} ms per view, ratio {ratio:.1}x (median of {ROUNDS} alternated rounds)",
                p * 1e3
            );
            perf_line(
                "structured light (Gray code)",
                "1280x1024, one view",
                ours,
                Some(("OpenCV structured_light + triangulatePoints", p, ratio)),
                Some("clouds/s"),
            );
        }
        Err(e) => {
            println!("structured light: peer unavailable ({e})");
            perf_line("structured light (Gray code)", "1280x1024, one view", ours, None, Some("clouds/s"));
        }
    }
    // 4-step phase shift with Gray-code unwrapping, columns and rows.
    let phase = PhaseShiftPatterns::new(proj.width, proj.height, 4, 16.0, Unwrapping::GrayCode, true).expect("layout");
    let images: Vec<Vec<u8>> = (0..phase.count()).map(|i| capture(&phase.render(i, None).expect("in range"))).collect();
    let imgs: Vec<&[u8]> = images.iter().map(Vec::as_slice).collect();
    let prm = PhaseDecodeParams::default();
    let mut stages = Stages::default();
    let mut points = 0;
    let ours = median_s(7, || {
        stages.start();
        let coords = phase.decode(&imgs, w as usize, h as usize, &prm).expect("decodes");
        stages.lap(0);
        triangulator.triangulate_into(&coords, None, &tri, &mut range).expect("triangulates");
        stages.lap(1);
        stages.passes.push(triangulator.last_pass_seconds());
        let cloud = range.valid_cloud();
        points = cloud.len();
        merged = PointCloud::new();
        merged.extend(cloud);
        stages.lap(2);
    });
    stages.print("4-step phase");
    println!(
        "structured light 4-step phase {w}x{h} ({} images): decode + triangulate + merge {:.1} ms ({:.1} clouds/s), {points} points",
        phase.count(),
        ours * 1e3,
        1.0 / ours
    );
    perf_line("structured light (4-step phase)", "1280x1024, one view", ours, None, Some("clouds/s"));
    black_box(merged);
}

/// A bowl on the ground plane z = 0: the solid sphere `outer` minus the sphere `pit` cut into its
/// top. Its visual hull from cameras above the rim keeps the pit full; only shadows cast by the rim
/// into the pit, seen from above, can carve it.
struct Bowl {
    centre: Vector3<f64>,
    radius: f64,
    pit_centre: Vector3<f64>,
    pit_radius: f64,
}

impl Bowl {
    fn contains(&self, p: &Vector3<f64>) -> bool {
        (p - self.centre).norm() <= self.radius && (p - self.pit_centre).norm() > self.pit_radius
    }

    /// Height of the rim, where the two spheres meet.
    fn rim_z(&self) -> f64 {
        let (zc, zp) = (self.centre.z, self.pit_centre.z);
        (self.radius.powi(2) - self.pit_radius.powi(2)) / (2.0 * (zp - zc)) + (zc + zp) / 2.0
    }

    /// First point (distance, outward normal) where the unit ray `o + t d`, `t > 1e-9`, enters the
    /// solid: the outer sphere outside the pit, or the pit's wall from inside the pit.
    fn hit(&self, o: &Vector3<f64>, d: &Vector3<f64>) -> Option<(f64, Vector3<f64>)> {
        let interval = |c: &Vector3<f64>, r: f64| {
            let oc = o - c;
            let b = oc.dot(d);
            let disc = b * b - (oc.norm_squared() - r * r);
            (disc >= 0.0).then(|| (-b - disc.sqrt(), -b + disc.sqrt()))
        };
        let (a0, a1) = interval(&self.centre, self.radius)?;
        let pit = interval(&self.pit_centre, self.pit_radius);
        let in_pit = |t: f64| pit.is_some_and(|(b0, b1)| t > b0 && t < b1);
        let mut best: Option<(f64, Vector3<f64>)> = None;
        if a0 > 1e-9 && !in_pit(a0) {
            best = Some((a0, (o + d * a0 - self.centre) / self.radius));
        }
        if let Some((_, b1)) = pit {
            if b1 > 1e-9 && b1 > a0 && b1 < a1 && best.is_none_or(|(t, _)| b1 < t) {
                best = Some((b1, (self.pit_centre - (o + d * b1)) / self.pit_radius));
            }
        }
        best
    }
}

/// Erosion of a mask by a `(2r+1)²` square, as `pipeline::detect_shadows` erodes its shadows.
fn erode(m: &Mask, r: i64) -> Mask {
    let (w, h) = (m.width() as i64, m.height() as i64);
    Mask::from_fn(m.width(), m.height(), |u, v| {
        (-r..=r).all(|dv| {
            (-r..=r).all(|du| {
                let (x, y) = (u as i64 + du, v as i64 + dv);
                x >= 0 && y >= 0 && x < w && y < h && m.get(x as u32, y as u32)
            })
        })
    })
}

fn shadow_carving() {
    // The bowl's upper bound: the outer sphere grown by two voxels and capped one voxel above the
    // rim (what silhouettes from above leave). 24 camera positions on a ring at 56 degrees
    // elevation, and per position 4 lights that turn with the camera (as on a turntable): one nearly
    // overhead behind the object, two high behind-left and behind-right, one low on the camera's
    // side, so that the rim shadows the pit where the camera sees it. The shadow masks are the
    // bowl's attached and cast shadows (and those on the ground), eroded 2 px as detection does.
    let bowl = Bowl {
        centre: Vector3::new(0.0, 0.0, 0.035),
        radius: 0.035,
        pit_centre: Vector3::new(0.0, 0.0, 0.06),
        pit_radius: 0.027,
    };
    let bbox = Aabb { min: [-0.045, -0.045, 0.0], max: [0.045, 0.045, 0.09] };
    let grid = VoxelGrid::from_resolution(&bbox, 128);
    let (vs, rim) = (grid.voxel_size, bowl.rim_z());
    let hull = Occupancy::from_fn(grid, |p| (p - bowl.centre).norm() <= bowl.radius + 2.0 * vs && p.z <= rim + vs);
    let truth = Occupancy::from_fn(grid, |p| bowl.contains(&p));
    let (w, h) = (640u32, 480u32);
    let target = Vector3::new(0.0, 0.0, 0.035);
    let around = |az: f64, el: f64, dist: f64| {
        let (az, el) = (az.to_radians(), el.to_radians());
        target + Vector3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin()) * dist
    };
    let mut positions = Vec::new();
    for i in 0..24 {
        let az = i as f64 * 15.0;
        let cam = CameraModel {
            width: w,
            height: h,
            intrinsics: intrinsics(w, h, 900.0),
            pose: Pose::look_at(around(az, 56.0, 0.5), target, Vector3::z()),
        };
        let lights: Vec<Vector3<f64>> = [(180.0, 85.0), (240.0, 65.0), (120.0, 65.0), (0.0, 30.0)]
            .iter()
            .map(|&(daz, el)| around(az + daz, el, 0.5))
            .collect();
        positions.push((cam, lights));
    }
    let setup_t = Instant::now();
    let masks: Vec<Vec<Mask>> = positions
        .iter()
        .map(|(cam, lights)| {
            let o = cam.centre();
            // Per pixel: the visible point and its normal (bowl or ground), then each light.
            let seen: Vec<Option<(Vector3<f64>, Vector3<f64>)>> = (0..w * h)
                .into_par_iter()
                .map(|i| {
                    let d = cam.pixel_ray((i % w) as f64 + 0.5, (i / w) as f64 + 0.5).normalize();
                    match bowl.hit(&o, &d) {
                        Some((t, n)) => Some((o + d * t, n)),
                        None if d.z < 0.0 => Some((o + d * (-o.z / d.z), Vector3::z())),
                        None => None,
                    }
                })
                .collect();
            lights
                .iter()
                .map(|l| {
                    let raw = Mask::from_fn(w, h, |u, v| {
                        let Some((p, n)) = seen[(v * w + u) as usize] else { return false };
                        let to_light = l - p;
                        let dist = to_light.norm();
                        let dir = to_light / dist;
                        n.dot(&dir) <= 0.0 || bowl.hit(&(p + n * 1e-7), &dir).is_some_and(|(t, _)| t < dist)
                    });
                    erode(&raw, 2)
                })
                .collect()
        })
        .collect();
    let views: Vec<ShadowView<'_>> = positions
        .iter()
        .zip(&masks)
        .flat_map(|((cam, lights), ms)| {
            lights.iter().zip(ms).map(|(l, m)| ShadowView { camera: *cam, light_m: *l, shadow: m })
        })
        .collect();
    let shadow_px: usize = masks.iter().flatten().map(Mask::count).sum();
    println!(
        "shadow carving scene: bowl (pit {:.1} mm deep), hull {} voxels, truth {}, {} shadow pixels over 96 views ({:.1} s to render)",
        (rim - (bowl.pit_centre.z - bowl.pit_radius)) * 1e3,
        hull.count(),
        truth.count(),
        shadow_px,
        setup_t.elapsed().as_secs_f64()
    );
    let params = ShadowCarveParams::default();
    let mut result = None;
    let ours = median_s(5, || {
        let (occ, stats) = carve_shadows(&hull, &views, &params).expect("carves");
        result = Some((occ, stats));
    });
    let (occ, stats) = result.expect("ran");
    let mut base_result = None;
    let base = median_s(3, || {
        base_result = Some(shadow_baseline::carve_shadows_baseline(&hull, &views, &params));
    });
    let (base_occ, base_stats) = base_result.expect("ran");
    let fit = |o: &Occupancy| o.iou_and_containment(&truth).expect("same grid");
    let (before, after) = (fit(&hull), fit(&occ));
    let same = occ.same_voxels(&base_occ);
    println!(
        "shadow carving 128^3, 24 positions x 4 lights: {ours:.3} s, {} voxels carved ({} rounds, {} candidates); IoU with the bowl {:.4} -> {:.4}, containment {:.4} -> {:.4}",
        stats.removed, stats.sweeps, stats.candidates, before.iou, after.iou, before.containment, after.containment
    );
    println!(
        "shadow carving baseline (sweeps over every candidate): {base:.3} s, {} voxels carved ({} sweeps); same voxels: {same}; ratio {:.1}x",
        base_stats.removed,
        base_stats.sweeps,
        base / ours
    );
    assert!(same, "the shadow carving differs from the baseline's");
    // Streaming, as the scan does it: each position carved as it arrives; what remains after the
    // last frame is the last position's carving and the read-out.
    let mut last = 0.0;
    let streamed = median_s(3, || {
        let mut carver = ShadowCarver::new(&hull, &params).expect("grid");
        for (i, ((cam, lights), ms)) in positions.iter().zip(&masks).enumerate() {
            let lights = lights.iter().copied().zip(ms.iter().cloned()).collect();
            let t = Instant::now();
            carver.add_position(*cam, lights).expect("carves");
            if i + 1 == positions.len() {
                black_box(carver.occupancy());
                last = t.elapsed().as_secs_f64();
            }
        }
    });
    println!(
        "shadow carving streamed per position: {streamed:.3} s in all, last position + read-out {:.1} ms (target <= 0.5 s after the last frame)",
        last * 1e3
    );
    perf_line(
        "shadow carving",
        "128^3, 24 positions x 4 lights",
        ours,
        Some(("sweeps over every candidate (before)", base, base / ours)),
        None,
    );
}

/// Mesh simplification at the scans' default bound (a quarter voxel) on a 128^3 carved solid the size
/// of the shipped rigs' (a lumpy ball with a pit and a handle, about 340,000 triangles): the mesh cut
/// into regions simplified in parallel (what the scans run) against every collapse made one after the
/// other on the whole mesh (before), same run.
fn mesh_simplification() {
    let grid = VoxelGrid::from_resolution(&Aabb { min: [-0.06; 3], max: [0.06; 3] }, 128);
    let occ = Occupancy::from_fn(grid, |p| {
        let (x, y, z) = (p.x / 0.05, p.y / 0.05, p.z / 0.05);
        let lumps = 0.06 * (7.0 * x).sin() * (5.0 * y).cos() + 0.04 * (9.0 * z).sin();
        let ball = x * x + y * y + z * z < (0.85 + lumps) * (0.85 + lumps);
        let pit = (x - 0.3).powi(2) + (y - 0.2).powi(2) < 0.04 && z > 0.2;
        let r = ((x + 0.2).powi(2) + z * z).sqrt() - 0.45;
        let handle = r * r + (y - 0.9).powi(2) < 0.12 * 0.12;
        (ball && !pit) || handle
    });
    let mesh = extract_surface(&occ, &MeshParams::smoothed(0)).expect("mesh");
    let params = SimplifyParams { max_error_m: 0.25 * grid.voxel_size };
    let mut ours_mesh = None;
    let ours = median_s(5, || ours_mesh = Some(simplify(&mesh, &params)));
    let mut base_mesh = None;
    let base = median_s(3, || base_mesh = Some(simplify_in(&mesh, &params, 1)));
    let ((ours_mesh, ours_stats), (base_mesh, base_stats)) = (ours_mesh.expect("ran"), base_mesh.expect("ran"));
    let check = |m| hausdorff_distance(m, &mesh, 100_000).expect("distance").symmetric_m;
    let (ours_h, base_h) = (check(&ours_mesh), check(&base_mesh));
    println!(
        "mesh simplification 128^3, {} triangles, bound {:.4} mm: {ours:.3} s -> {} triangles, Hausdorff {:.4} mm; \
         one region (before) {base:.3} s -> {} triangles, Hausdorff {:.4} mm; ratio {:.1}x",
        mesh.triangles.len(),
        params.max_error_m * 1e3,
        ours_stats.triangles_after,
        ours_h * 1e3,
        base_stats.triangles_after,
        base_h * 1e3,
        base / ours
    );
    assert!(ours_h <= params.max_error_m && base_h <= params.max_error_m, "bound exceeded");
    perf_line(
        "mesh simplification",
        &format!("128^3 solid, {} triangles, 0.25 voxel", mesh.triangles.len()),
        ours,
        Some(("one region, collapses in sequence (before)", base, base / ours)),
        None,
    );
}

fn main() {
    // `cargo bench --bench methods -- NAME...` runs only the named cases (tsdf, laser,
    // structured-light, shadow, mesh); `cargo bench` itself passes `--bench`, which is not a name.
    let names: Vec<String> = std::env::args().skip(1).filter(|a| !a.starts_with("--")).collect();
    let wanted = |case: &str| names.is_empty() || names.iter().any(|n| n == case);
    let dir = tempfile::tempdir().expect("temporary directory");
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!(
        "machine: {} cores, load average {}",
        std::thread::available_parallelism().map_or(0, |n| n.get()),
        load.trim()
    );
    if wanted("tsdf") {
        tsdf(dir.path());
    }
    if wanted("laser") {
        laser(dir.path());
    }
    if wanted("structured-light") {
        structured_light();
    }
    if wanted("shadow") {
        shadow_carving();
    }
    if wanted("mesh") {
        mesh_simplification();
    }
}

#!/usr/bin/env python3
"""Time Open3D's silhouette carving on a calibrated image set and compare with scanrig.

Usage:
    pip install open3d numpy
    cargo build --release
    python3 benches/open3d_peer.py --dataset DIR [--calibration FILE|DIR] [--views LIST] [--bbox BOX]
        [--masks DIR | --silhouette threshold=T,dilate=D,erode=E] [--resolution 256]
        [--scanrig target/release/scanrig] [--inputs-only]

DIR is any data set `scanrig reconstruct` reads: a Middlebury `*_par.txt` (the default calibration: the
one in DIR), a file of 3x4 projection matrices (`name p11 .. p34`, either sign), or a COLMAP text model
(a directory with cameras.txt and images.txt; pinhole models only, Open3D carves without distortion), or
an OpenCV FileStorage file (YAML or XML: one camera without distortion, extrinsic_parameters with a row
per view, the image names in `images`; read with OpenCV).
--views defaults to DIR/*_good_silhouette_images.txt when there is one, else every calibrated view;
--bbox defaults to the Middlebury dino's tight box (give it for any other set). --inputs-only reads and
prints the inputs without Open3D (a check of the loaders).

Both sides use the same inputs: the 15 good views, the authors' silhouette recipe (threshold 0.19 on
max(R,G,B) scaled to 0..1, dilate with a disc of 10 px, erode with a disc of 7 px; pixels outside the
image do not erode), the cameras P = K [R | t] from the par file, and the data set's tight bounding box
with RESOLUTION voxels along its longest side. Open3D's grid is built with VoxelGrid.create_dense and
carved with carve_silhouette(keep_voxels_outside_image=True); its grid build is timed apart.
scanrig is run as `scanrig reconstruct --dataset DIR --method space-carving --resolution N --bbox BOX
--calibration CAL --views NAMES --silhouette S (or --masks DIR) --out OUT`
several times and the median of its carve time, read from OUT/report.json (timings_s.carve, which
includes building the per-view summed-area tables), is compared.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

BOX_MIN = np.array([-0.061897, -0.018874, -0.057845])
BOX_MAX = np.array([0.010897, 0.068227, 0.015495])


def read_par(path):
    with open(path) as f:
        lines = [l.split() for l in f if l.strip() and not l.startswith("#")]
    count = int(lines[0][0])
    cams = {}
    for tok in lines[1 : 1 + count]:
        v = np.array([float(x) for x in tok[1:]])
        cams[tok[0]] = (v[0:9].reshape(3, 3), v[9:18].reshape(3, 3), v[18:21])
    return cams


def decompose(p, scene):
    """K, R, t of P with the sign that puts `scene` in front of the camera (as scanrig does)."""
    if scene is not None:
        p = p * np.sign((p @ np.append(scene, 1.0))[2])
    elif np.linalg.det(p[:, :3]) < 0:
        p = -p
    m = p[:, :3]
    # RQ via QR of the row-reversed transpose.
    q, r = np.linalg.qr(np.flipud(m).T)
    k = np.flipud(np.fliplr(r.T))
    rot = np.flipud(q.T)
    s = np.diag(np.sign(np.diag(k)))
    k, rot = k @ s, s @ rot
    t = np.linalg.solve(k, p[:, 3])
    return k / k[2, 2], rot, t


def convergence(ps):
    a, b = np.zeros((3, 3)), np.zeros(3)
    for p in ps:
        c = -np.linalg.solve(p[:, :3], p[:, 3])
        d = p[2, :3] / np.linalg.norm(p[2, :3])
        pr = np.eye(3) - np.outer(d, d)
        a += pr
        b += pr @ c
    if len(ps) < 2 or np.linalg.eigvalsh(a).min() <= 1e-6 * len(ps):
        return None
    return np.linalg.solve(a, b)


def read_projections(path):
    rows = []
    with open(path) as f:
        for l in f:
            t = l.split()
            if t and not t[0].startswith("#"):
                rows.append((t[0], np.array([float(x) for x in t[1:13]]).reshape(3, 4)))
    scene = convergence([p for _, p in rows])
    return {n: decompose(p, scene) for n, p in rows}


def quat_to_r(w, x, y, z):
    n = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def read_colmap(d):
    intr = {}
    with open(os.path.join(d, "cameras.txt")) as f:
        for l in f:
            t = l.split()
            if not t or t[0].startswith("#"):
                continue
            v = [float(x) for x in t[4:]]
            if t[1] == "SIMPLE_PINHOLE":
                fx = fy = v[0]
                cx, cy = v[1], v[2]
            elif t[1] == "PINHOLE":
                fx, fy, cx, cy = v[:4]
            else:
                sys.exit(f"{d}/cameras.txt: camera model {t[1]}: Open3D carves pinhole cameras only")
            # COLMAP's top-left pixel centre is (0.5, 0.5); Open3D's is (0, 0).
            intr[t[0]] = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1.0]])
    cams = {}
    with open(os.path.join(d, "images.txt")) as f:
        lines = [l.strip() for l in f if not l.startswith("#")]
    i = 0
    while i < len(lines):
        if not lines[i]:
            i += 1
            continue
        t = lines[i].split()
        v = [float(x) for x in t[1:8]]
        cams[" ".join(t[9:])] = (intr[t[8]], quat_to_r(*v[:4]), np.array(v[4:7]), "open3d-pixels")
        i += 2
    return cams


def read_opencv(path):
    """One camera and per-view extrinsics of an OpenCV FileStorage file (YAML or XML), as scanrig's
    `reconstruct --dataset` reads it: camera_matrix (or cameraMatrix, K), distortion (must be zero:
    Open3D carves pinhole cameras), extrinsic_parameters (a row per view: Rodrigues vector,
    translation) and the image names in the `images` sequence."""
    try:
        import cv2
    except ImportError:
        sys.exit(f"{path}: reading OpenCV FileStorage needs OpenCV: pip install opencv-python-headless")
    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    node = lambda *names: next((fs.getNode(n) for n in names if not fs.getNode(n).empty()), None)
    k = node("camera_matrix", "cameraMatrix", "K", "cam_int", "M1")
    if k is None:
        sys.exit(f"{path}: no camera_matrix")
    d = node("distortion_coefficients", "distCoeffs", "dist_coeffs", "D", "cam_dist", "D1")
    if d is not None and np.any(d.mat() != 0):
        sys.exit(f"{path}: non-zero lens distortion: Open3D carves pinhole cameras only")
    ext, images = fs.getNode("extrinsic_parameters"), fs.getNode("images")
    if ext.empty() or images.empty():
        sys.exit(f"{path}: needs extrinsic_parameters and an images sequence")
    names = [images.at(i).string() for i in range(images.size())]
    rows = ext.mat().reshape(-1, 6)
    if len(names) != len(rows):
        sys.exit(f"{path}: {len(names)} image names for {len(rows)} views")
    # OpenCV's pixel centres are at integer coordinates, as Open3D's.
    return {n: (k.mat(), cv2.Rodrigues(row[:3])[0], row[3:], "open3d-pixels") for n, row in zip(names, rows)}


def read_calibration(path):
    if os.path.isdir(path) or os.path.basename(path) in ("cameras.txt", "images.txt"):
        return read_colmap(path if os.path.isdir(path) else os.path.dirname(path))
    with open(path) as f:
        head = f.read(4096)
    if head.lstrip().startswith("%YAML") or "<opencv_storage" in head:
        return read_opencv(path)
    first = next((l for l in head.splitlines() if l.strip() and not l.startswith("#")), "")
    return read_par(path) if len(first.split()) == 1 else read_projections(path)


def disc_offsets(r):
    return [(dx, dy) for dy in range(-r, r + 1) for dx in range(-r, r + 1) if dx * dx + dy * dy <= r * r]


def dilate(mask, r, outside):
    """Binary dilation with a disc of radius r; pixels outside the image count as `outside`."""
    if r == 0:
        return mask.copy()
    h, w = mask.shape
    padded = np.pad(mask, r, constant_values=outside)
    out = np.zeros_like(mask)
    for dx, dy in disc_offsets(r):
        out |= padded[r + dy : r + dy + h, r + dx : r + dx + w]
    return out


def recipe_mask(rgb, threshold=0.19, dil=10, ero=7):
    obj = rgb.max(axis=2).astype(np.float32) / 255.0 > threshold
    closed = dilate(obj, dil, False)
    return ~dilate(~closed, ero, False)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", required=True)
    ap.add_argument("--calibration", help="calibration file or COLMAP directory (default: DIR/*_par.txt)")
    ap.add_argument("--views", help="file with one image name per line (default: DIR/*_good_silhouette_images.txt)")
    ap.add_argument("--bbox", help="xmin,ymin,zmin,xmax,ymax,zmax in metres (default: the dino's tight box)")
    ap.add_argument("--masks", help="directory of masks, same stems, PNG, non-zero = object")
    ap.add_argument("--silhouette", default="threshold=0.19,dilate=10,erode=7")
    ap.add_argument("--inputs-only", action="store_true", help="read and print the inputs, no Open3D")
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--scanrig", default=os.path.join("target", "release", "scanrig"))
    ap.add_argument("--runs", type=int, default=5, help="scanrig runs (the median carve time is used)")
    args = ap.parse_args()

    cal = args.calibration
    if cal is None:
        pars = sorted(f for f in os.listdir(args.dataset) if f.endswith("_par.txt"))
        if not pars:
            sys.exit(f"{args.dataset}: no *_par.txt; give --calibration")
        cal = os.path.join(args.dataset, pars[0])
    cams = read_calibration(cal)
    views_file = args.views
    if views_file is None:
        good = sorted(f for f in os.listdir(args.dataset) if f.endswith("_good_silhouette_images.txt"))
        views_file = os.path.join(args.dataset, good[0]) if good else None
    if views_file:
        with open(views_file) as f:
            names = [l.strip() for l in f if l.strip() and not l.startswith("#")]
    else:
        names = list(cams)
    box_min, box_max = BOX_MIN, BOX_MAX
    if args.bbox:
        b = [float(x) for x in args.bbox.split(",")]
        box_min, box_max = np.array(b[:3]), np.array(b[3:])
    sil = dict(kv.split("=") for kv in args.silhouette.split(","))
    thr, dil, ero = float(sil.get("threshold", 0.19)), int(sil.get("dilate", 10)), int(sil.get("erode", 7))
    print(f"{len(names)} views from {cal}, box {box_min.tolist()} .. {box_max.tolist()}")
    if args.inputs_only:
        for n in names[:3]:
            k, r, t = cams[n][:3]
            centre = -r.T @ t
            print(f"  {n}: fx {k[0, 0]:.2f} fy {k[1, 1]:.2f} cx {k[0, 2]:.2f} cy {k[1, 2]:.2f}, centre {centre.round(4).tolist()}, "
                  f"det R {np.linalg.det(r):+.0f}")
        return
    try:
        import open3d as o3d
    except ImportError:  # pragma: no cover - the script's only hard requirement
        sys.exit("this script needs Open3D: pip install open3d")

    views = []
    for name in names:
        rgb = np.asarray(o3d.io.read_image(os.path.join(args.dataset, name)))
        if args.masks:
            stem = os.path.splitext(os.path.basename(name))[0]
            mask = np.asarray(o3d.io.read_image(os.path.join(args.masks, stem + ".png"))) != 0
            if mask.ndim == 3:
                mask = mask.any(axis=2)
        else:
            mask = recipe_mask(rgb[:, :, :3] if rgb.ndim == 3 else np.stack([rgb] * 3, axis=2), thr, dil, ero)
        k, r, t = cams[name][:3]
        h, w = mask.shape
        params = o3d.camera.PinholeCameraParameters()
        params.intrinsic = o3d.camera.PinholeCameraIntrinsic(w, h, k[0, 0], k[1, 1], k[0, 2], k[1, 2])
        ext = np.eye(4)
        ext[:3, :3] = r
        ext[:3, 3] = t
        params.extrinsic = ext
        # carve_silhouette reads the mask as 32-bit float (object > 0); an 8-bit image carves nothing.
        img = o3d.geometry.Image(mask.astype(np.float32))
        views.append((img, params))

    extent = box_max - box_min
    size = extent.max() / args.resolution
    dims = np.ceil(extent / size - 1e-9).astype(int)
    t0 = time.perf_counter()
    grid = o3d.geometry.VoxelGrid.create_dense(
        box_min, np.array([1.0, 1.0, 1.0]), size, *(dims * size)
    )
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    for img, params in views:
        grid.carve_silhouette(img, params, keep_voxels_outside_image=True)
    t_o3d = time.perf_counter() - t0
    n_o3d = len(grid.get_voxels())
    print(f"Open3D {o3d.__version__}: grid {dims.tolist()}, build {t_build:.2f} s, carve {t_o3d:.2f} s, {n_o3d} voxels")

    box = ",".join(f"{x:.6f}" for x in [*box_min, *box_max])
    times = []
    for _ in range(args.runs):
        with tempfile.TemporaryDirectory() as out:
            cmd = [
                args.scanrig, "reconstruct", "--dataset", args.dataset, "--method", "space-carving",
                "--resolution", str(args.resolution), f"--bbox={box}",
                "--calibration", cal, "--views", ",".join(names), "--out", out,
            ]
            cmd += ["--masks", args.masks] if args.masks else ["--silhouette", args.silhouette]
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            with open(os.path.join(out, "report.json")) as f:
                report = json.load(f)
        times.append(float(report["timings_s"]["carve"]))
    times.sort()
    t_ours = times[len(times) // 2]
    print(f"scanrig: carve median of {args.runs} runs {t_ours * 1e3:.1f} ms (min {times[0] * 1e3:.1f} ms), "
          f"{report['occupied_voxels']} voxels, grid {report['resolution']}")
    print(f"speed-up over Open3D carve_silhouette: {t_o3d / t_ours:.0f}x (Open3D carve only; "
          f"{(t_o3d + t_build) / t_ours:.0f}x with its grid build)")


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""Time Open3D's silhouette carving on the Middlebury dino data set and compare with scanrig.

Usage:
    pip install open3d numpy
    cargo build --release
    python3 benches/open3d_peer.py --dataset DIR [--resolution 256] [--scanrig target/release/scanrig]

DIR holds dinoSR0001.png .. dinoSR0016.png, dinoSR_par.txt and dinoSR_good_silhouette_images.txt
(the Middlebury multi-view stereo "dinoSparseRing" set; Seitz et al., CVPR 2006).

Both sides use the same inputs: the 15 good views, the authors' silhouette recipe (threshold 0.19 on
max(R,G,B) scaled to 0..1, dilate with a disc of 10 px, erode with a disc of 7 px; pixels outside the
image do not erode), the cameras P = K [R | t] from the par file, and the data set's tight bounding box
with RESOLUTION voxels along its longest side. Open3D's grid is built with VoxelGrid.create_dense and
carved with carve_silhouette(keep_voxels_outside_image=True); its grid build is timed apart.
scanrig is run as `scanrig reconstruct --dataset DIR --method space-carving --resolution N --bbox BOX
--views DIR/dinoSR_good_silhouette_images.txt --silhouette threshold=0.19,dilate=10,erode=7 --out OUT`
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

try:
    import open3d as o3d
except ImportError:  # pragma: no cover - the script's only hard requirement
    sys.exit("this script needs Open3D: pip install open3d")

BOX_MIN = np.array([-0.061897, -0.018874, -0.057845])
BOX_MAX = np.array([0.010897, 0.068227, 0.015495])


def read_par(path):
    with open(path) as f:
        lines = [l.split() for l in f if l.strip()]
    count = int(lines[0][0])
    cams = {}
    for tok in lines[1 : 1 + count]:
        v = np.array([float(x) for x in tok[1:]])
        cams[tok[0]] = (v[0:9].reshape(3, 3), v[9:18].reshape(3, 3), v[18:21])
    return cams


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


def recipe_mask(rgb):
    obj = rgb.max(axis=2).astype(np.float32) / 255.0 > 0.19
    closed = dilate(obj, 10, False)
    return ~dilate(~closed, 7, False)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", required=True)
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--scanrig", default=os.path.join("target", "release", "scanrig"))
    ap.add_argument("--runs", type=int, default=5, help="scanrig runs (the median carve time is used)")
    args = ap.parse_args()

    cams = read_par(os.path.join(args.dataset, "dinoSR_par.txt"))
    with open(os.path.join(args.dataset, "dinoSR_good_silhouette_images.txt")) as f:
        names = [l.strip() for l in f if l.strip()]

    views = []
    for name in names:
        rgb = np.asarray(o3d.io.read_image(os.path.join(args.dataset, name)))[:, :, :3]
        mask = recipe_mask(rgb)
        k, r, t = cams[name]
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

    extent = BOX_MAX - BOX_MIN
    size = extent.max() / args.resolution
    dims = np.ceil(extent / size - 1e-9).astype(int)
    t0 = time.perf_counter()
    grid = o3d.geometry.VoxelGrid.create_dense(
        BOX_MIN, np.array([1.0, 1.0, 1.0]), size, *(dims * size)
    )
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    for img, params in views:
        grid.carve_silhouette(img, params, keep_voxels_outside_image=True)
    t_o3d = time.perf_counter() - t0
    n_o3d = len(grid.get_voxels())
    print(f"Open3D {o3d.__version__}: grid {dims.tolist()}, build {t_build:.2f} s, carve {t_o3d:.2f} s, {n_o3d} voxels")

    box = ",".join(f"{x:.6f}" for x in [*BOX_MIN, *BOX_MAX])
    times = []
    for _ in range(args.runs):
        with tempfile.TemporaryDirectory() as out:
            cmd = [
                args.scanrig, "reconstruct", "--dataset", args.dataset, "--method", "space-carving",
                "--resolution", str(args.resolution), f"--bbox={box}",
                "--views", os.path.join(args.dataset, "dinoSR_good_silhouette_images.txt"),
                "--silhouette", "threshold=0.19,dilate=10,erode=7", "--out", out,
            ]
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

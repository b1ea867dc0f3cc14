#!/usr/bin/env python3
"""Open3D peer of `cargo bench --bench methods` (TSDF depth fusion).

Usage: python3 benches/tsdf_open3d_peer.py SPEC.json   (pip install open3d-cpu numpy)

SPEC.json (written by the bench) names 16-bit PNG depth maps in millimetres, the pinhole
intrinsics, each view's 4x4 world-to-camera extrinsic, the cubic volume (origin, edge length,
voxels per edge) and the truncation distance (metres). The depth maps are fused into an
`o3d.pipelines.integration.UniformTSDFVolume` (no colour) with the same values; the files are read
before timing. Prints `PEER_S <seconds>`: the median over 5 runs of creating the volume and
integrating every view.
"""

import json
import os
import sys
import time

import numpy as np

try:
    import open3d as o3d
except ImportError:
    sys.exit("this script needs Open3D: pip install open3d-cpu")


def main():
    spec_path = sys.argv[1]
    with open(spec_path) as f:
        spec = json.load(f)
    base = os.path.dirname(spec_path)
    intr = o3d.camera.PinholeCameraIntrinsic(spec["width"], spec["height"], spec["fx"], spec["fy"], spec["cx"], spec["cy"])
    views = []
    for v in spec["views"]:
        depth = o3d.io.read_image(os.path.join(base, v["depth"]))
        colour = o3d.geometry.Image(np.zeros((spec["height"], spec["width"], 3), dtype=np.uint8))
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            colour, depth, depth_scale=1000.0, depth_trunc=10.0, convert_rgb_to_intensity=False
        )
        views.append((rgbd, np.array(v["extrinsic"], dtype=np.float64)))
    times = []
    for _ in range(5):
        t = time.perf_counter()
        vol = o3d.pipelines.integration.UniformTSDFVolume(
            length=spec["length"],
            resolution=spec["resolution"],
            sdf_trunc=spec["sdf_trunc"],
            color_type=o3d.pipelines.integration.TSDFVolumeColorType.NoColor,
            origin=np.array(spec["origin"], dtype=np.float64).reshape(3, 1),
        )
        for rgbd, ext in views:
            vol.integrate(rgbd, intr, ext)
        times.append(time.perf_counter() - t)
    times.sort()
    mesh = vol.extract_triangle_mesh()
    print(f"open3d {o3d.__version__} UniformTSDFVolume {spec['resolution']}^3, {len(views)} views: "
          f"{times[len(times) // 2]:.3f} s, mesh {len(mesh.triangles)} triangles")
    print(f"PEER_S {times[len(times) // 2]}")


if __name__ == "__main__":
    main()

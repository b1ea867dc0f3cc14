#!/usr/bin/env python3
"""Peer benchmark for one structured-light view: OpenCV Gray-code decode plus cv2.triangulatePoints.

Usage: python3 benches/opencv_sl_peer.py SPEC.json [--repeat 3]

SPEC.json (written by `cargo bench --bench methods -- structured-light`) holds the camera and
projector calibration (pinhole: fx, fy, cx, cy, world-to-camera rotation and translation) and the
path of a raw little-endian int32 file: per camera pixel (row-major), the projector pixel index
`v * projector_width + u` that lights it, or -1. That is the same lookup the Rust bench captures its
own patterns through (the plane y = 0 seen by both).

Not timed: OpenCV's patterns are generated with GrayCodePattern.generate() and the captured images
are synthesised through the lookup exactly as the Rust bench does (30 + value * 180 / 255 where lit,
10 elsewhere), with OpenCV's white and black images.

Timed, per view (median of --repeat):
  1. GrayCodePattern.decode on the synthesised stack. decode is OpenCV's only bulk decoder; it is a
     stereo entry point, so the capture is handed in as both cameras and it decodes 2 x width x
     height pixels and matches them into a disparity map (this flatters the Rust side somewhat).
  2. cv2.triangulatePoints of every lit camera pixel centre with its projector pixel centre, with
     the projection matrices K [R | t] of the same calibration, and the division by w. decode does
     not return projector coordinates, so the correspondences come from the lookup (what a correct
     decoder yields); building those arrays is outside the timing.
Needs `pip install opencv-contrib-python-headless numpy`. Last line: `PEER_S <seconds>`.
"""
import argparse
import json
import statistics
import time

import cv2
import numpy as np


def projection(m):
    k = np.array([[m["fx"], 0.0, m["cx"]], [0.0, m["fy"], m["cy"]], [0.0, 0.0, 1.0]])
    rt = np.hstack([np.array(m["rotation"]), np.array(m["translation"]).reshape(3, 1)])
    return k @ rt


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("spec")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    with open(a.spec) as f:
        spec = json.load(f)
    cam, proj = spec["camera"], spec["projector"]
    w, h = cam["width"], cam["height"]
    pw, ph = proj["width"], proj["height"]
    lookup = np.fromfile(spec["lookup"], dtype="<i4")
    assert lookup.size == w * h
    lit = lookup >= 0
    idx = np.where(lit, lookup, 0)

    gc = cv2.structured_light.GrayCodePattern.create(pw, ph)
    ok, patterns = gc.generate()
    assert ok
    white_p = np.full((ph, pw), 255, np.uint8)
    black_p = np.zeros((ph, pw), np.uint8)

    def capture(p):
        v = 30 + p.reshape(-1)[idx].astype(np.uint32) * 180 // 255
        return np.where(lit, v, 10).astype(np.uint8).reshape(h, w)

    pats = [capture(p) for p in patterns]
    white, black = capture(white_p), capture(black_p)

    ys, xs = np.divmod(np.nonzero(lit)[0], w)
    cam_pts = np.vstack([xs + 0.5, ys + 0.5]).astype(np.float64)
    pv, pu = np.divmod(lookup[lit], pw)
    proj_pts = np.vstack([pu + 0.5, pv + 0.5]).astype(np.float64)
    pc, pp = projection(cam), projection(proj)

    times = []
    for _ in range(a.repeat):
        t = time.perf_counter()
        gc.decode([pats, pats], blackImages=[black, black], whiteImages=[white, white])
        x = cv2.triangulatePoints(pc, pp, cam_pts, proj_pts)
        pts = (x[:3] / x[3]).T
        times.append(time.perf_counter() - t)
    s = statistics.median(times)
    print(f"OpenCV {cv2.__version__}: {len(patterns)} patterns {pw}x{ph}, camera {w}x{h}, "
          f"{pts.shape[0]} points (bench: {spec['points']}), mean |y| {np.abs(pts[:, 1]).mean():.2e} m, "
          f"decode + triangulatePoints median {s * 1e3:.1f} ms")
    print(f"PEER_S {s}")


if __name__ == "__main__":
    main()

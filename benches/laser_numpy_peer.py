#!/usr/bin/env python3
"""numpy/OpenCV peer of `cargo bench --bench methods` (laser stripe extraction + triangulation).

Usage: python3 benches/laser_numpy_peer.py SPEC.json   (pip install numpy opencv-contrib-python-headless)

The same algorithm as `pipeline::laser::detect_stripe` + `triangulate_peaks`, vectorised with numpy:
signal = red-weighted difference of the laser-on and laser-off frames; per row, runs of pixels at or
above `min_peak` no wider than `max_width` give one peak each: the centroid (pixel centres, weights
max(signal, 0)) over `half_window` pixels each side of the run's maximum; each peak's camera ray
meets the laser plane. Frames are read (cv2.imread) before timing. Prints the point count (which
must match the bench's) and `PEER_S <seconds per frame>`, the median over 51 runs.
"""

import json
import sys
import time

import cv2
import numpy as np


def extract(off, on, spec, K_inv, R_t, centre, n, offset):
    signal = on[:, :, 2].astype(np.float32) - off[:, :, 2].astype(np.float32)  # BGR: red channel
    h, w = signal.shape
    above = signal >= spec["min_peak"]
    # Run starts and ends per row.
    pad = np.zeros((h, 1), dtype=bool)
    edges = np.diff(np.concatenate([pad, above, pad], axis=1).astype(np.int8), axis=1)
    rs, cs = np.nonzero(edges == 1)
    re, ce = np.nonzero(edges == -1)
    width = ce - cs
    keep = width <= spec["max_width"]
    rows, starts, ends = rs[keep], cs[keep], ce[keep]
    # Maximum within each run (runs are at most max_width long).
    offsets = np.arange(spec["max_width"])
    idx = starts[:, None] + offsets[None, :]
    valid = idx < ends[:, None]
    vals = np.where(valid, signal[rows[:, None], np.minimum(idx, w - 1)], -np.inf)
    imax = starts + np.argmax(vals, axis=1)
    hw = spec["half_window"]
    win = imax[:, None] + np.arange(-hw, hw + 1)[None, :]
    inside = (win >= 0) & (win < w)
    wgt = np.where(inside, np.maximum(signal[rows[:, None], np.clip(win, 0, w - 1)], 0.0), 0.0).astype(np.float64)
    sw = wgt.sum(axis=1)
    ok = sw > 0
    u = (wgt * (win + 0.5)).sum(axis=1)[ok] / sw[ok]
    v = rows[ok] + 0.5
    # Rays in the rig frame and their intersection with the plane n.x = offset.
    pix = np.stack([u, v, np.ones_like(u)], axis=0)
    rays = R_t @ (K_inv @ pix)
    denom = n @ rays
    t = (offset - n @ centre) / denom
    front = (np.abs(denom) >= 1e-12) & (t > 0)
    return (centre[:, None] + rays[:, front] * t[front]).T


def main():
    with open(sys.argv[1]) as f:
        spec = json.load(f)
    off = cv2.imread(spec["off"], cv2.IMREAD_COLOR)
    on = cv2.imread(spec["on"], cv2.IMREAD_COLOR)
    K = np.array([[spec["fx"], 0, spec["cx"]], [0, spec["fy"], spec["cy"]], [0, 0, 1]], dtype=np.float64)
    R = np.array(spec["rotation"], dtype=np.float64)
    t = np.array(spec["translation"], dtype=np.float64)
    centre = -R.T @ t
    n = np.array(spec["plane_normal"], dtype=np.float64)
    args = (off, on, spec, np.linalg.inv(K), R.T, centre, n, spec["plane_offset"])
    pts = extract(*args)
    times = []
    for _ in range(51):
        s = time.perf_counter()
        extract(*args)
        times.append(time.perf_counter() - s)
    times.sort()
    print(f"numpy {np.__version__}, OpenCV {cv2.__version__}: {off.shape[1]}x{off.shape[0]} "
          f"{times[25] * 1e3:.3f} ms per frame, {len(pts)} points (scanrig {spec['points']})")
    print(f"PEER_S {times[25]}")


if __name__ == "__main__":
    main()

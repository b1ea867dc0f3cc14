#!/usr/bin/env python3
"""Peer benchmark: OpenCV's GrayCodePattern.decode against `scanrig decode` on the same images, same run.

Usage: python3 benches/opencv_graycode_peer.py CAPTURE_DIR [--scanrig target/release/scanrig] [--repeat 5]

CAPTURE_DIR holds the 42 images of a 1024x768 projector's Gray-code sequence (20 pattern/inverse pairs,
white, black), sorted by name, e.g. the full chessboard capture or tests/fixtures/graycode/capture_crop.
Needs `pip install opencv-contrib-python-headless numpy`.

OpenCV's decode is its stereo entry point: it takes the pattern stacks of two cameras, decodes every
pixel of both (getProjPixel plus the shadow masks from the white/black images) and matches them into
a disparity map. We hand it the capture as both cameras, so it decodes 2 x width x height pixels; its
throughput is counted over those pixels. That includes its matching step, so the ratio flatters us
somewhat; the per-pixel decode is its bulk (getProjPixel called per pixel).
"""
import argparse
import glob
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import cv2
import numpy as np


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("capture")
    ap.add_argument("--scanrig", default=os.path.join(os.path.dirname(__file__), "..", "target", "release", "scanrig"))
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--black-threshold", type=int, default=40)
    ap.add_argument("--white-threshold", type=int, default=5)
    a = ap.parse_args()

    paths = sorted(p for p in glob.glob(os.path.join(a.capture, "*")) if p.lower().endswith(".png"))
    if len(paths) != 42:
        sys.exit(f"{a.capture}: {len(paths)} images, expected 42")
    imgs = [cv2.imread(p, cv2.IMREAD_GRAYSCALE) for p in paths]
    h, w = imgs[0].shape
    pats, white, black = imgs[:40], imgs[40], imgs[41]

    gc = cv2.structured_light.GrayCodePattern.create(1024, 768)
    gc.setBlackThreshold(a.black_threshold)
    gc.setWhiteThreshold(a.white_threshold)
    times = []
    for _ in range(a.repeat):
        t = time.perf_counter()
        ok, disparity = gc.decode([pats, pats], blackImages=[black, black], whiteImages=[white, white])
        times.append(time.perf_counter() - t)
    cv_s = statistics.median(times)
    cv_mpx = 2 * w * h / cv_s / 1e6

    # Valid fraction by OpenCV's per-pixel decoder on a sample of pixels, as a cross-check of thresholds.
    rng = np.random.default_rng(1)
    sample = rng.integers(0, [w, h], size=(2000, 2))
    shadow = np.abs(white.astype(int) - black.astype(int)) > a.black_threshold
    cv_valid = sum(1 for x, y in sample if shadow[y, x] and not gc.getProjPixel(pats, int(x), int(y))[0])

    with tempfile.TemporaryDirectory() as out:
        subprocess.run(
            [a.scanrig, "decode", "--images", a.capture, "--repeat", "21", "--out", out,
             "--black-threshold", str(a.black_threshold), "--white-threshold", str(a.white_threshold)],
            check=True, stdout=subprocess.DEVNULL)
        with open(os.path.join(out, "decode.json")) as f:
            ours = json.load(f)
    ours_mpx = ours["megapixels_per_s"]
    print(f"images {w}x{h}, OpenCV {cv2.__version__}")
    print(f"opencv GrayCodePattern.decode (2 cameras): median {cv_s * 1e3:.1f} ms, {cv_mpx:.2f} Mpx/s; "
          f"sampled valid fraction {cv_valid / len(sample):.3f}")
    print(f"scanrig decode: median {ours['decode_s_median'] * 1e3:.2f} ms, {ours_mpx:.1f} Mpx/s; "
          f"valid fraction {ours['valid_fraction']:.4f}")
    print(f"ratio scanrig / opencv: {ours_mpx / cv_mpx:.0f}x")


if __name__ == "__main__":
    main()

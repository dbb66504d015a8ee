#!/usr/bin/env python3
"""Checks dioptra's eyepiece model and pre-warp mesh against OpenCV's own camera model
(pip: opencv-python-headless numpy). For an eyepiece with different coefficients per colour
channel (radial k1-k3, tangential p1 p2, rational k4-k6, per-channel focal lengths):

- project: eye directions (x, y tangents) over the field through `dioptra optics --points
  project` against cv2.projectPoints of the points (x, y, 1) with no rotation or translation;
- unproject: panel pixels over the whole panel through `--points unproject` against
  cv2.undistortPoints iterated to convergence (undistortPointsIter in OpenCV 4; by default it
  stops after 5 iterations, whose error is printed for information), and reprojected by
  cv2.projectPoints;
- warp: panel pixels through the pre-warp mesh as it is drawn (`--points warp`: the source
  pixel each channel reads there, interpolated between the mesh's vertices), turned back into
  directions with the render intrinsics and projected by cv2.projectPoints: each must land on
  the panel pixel it was read for.

Every difference must be within 0.05 px over the field. Exit status 1 otherwise.
Usage: scripts/check_distortion_opencv.py [--binary target/debug/dioptra]"""
import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
TOLERANCE_PX = 0.05
PANEL = (1280, 720)
SOURCE = (960, 540)

# The render intrinsics and the shared coefficients, then each channel's own (OpenCV order:
# k1 k2 p1 p2 k3 k4 k5 k6).
RENDER = dict(fx=600.0, fy=604.0, cx=639.5, cy=361.0)
SHARED = dict(k1=-0.21, k2=0.045, p1=0.0007, p2=-0.0005, k3=-0.002, k4=0.01, k5=0.0, k6=0.0005)
CHANNELS = {
    "red": dict(fx=606.6, fy=610.0, k1=-0.215),
    "green": dict(),
    "blue": dict(fx=593.4, fy=597.5, cx=640.0, k2=0.05, k4=0.015),
}
ORDER = ["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"]


def channel(name):
    merged = {**RENDER, **SHARED, **CHANNELS[name]}
    k = np.array([[merged["fx"], 0, merged["cx"]], [0, merged["fy"], merged["cy"]], [0, 0, 1]],
                 dtype=np.float64)
    d = np.array([merged[c] for c in ORDER], dtype=np.float64)
    return k, d


def write_model(path):
    lines = ["[optics.distortion]"]
    lines += [f"{k} = {v!r}" for k, v in {**RENDER, **SHARED}.items()]
    for name, keys in CHANNELS.items():
        if keys:
            lines.append(f"[optics.distortion.{name}]")
            lines += [f"{k} = {v!r}" for k, v in keys.items()]
    path.write_text("\n".join(lines) + "\n")


def dioptra(binary, model, mode, points):
    cmd = [binary, "optics", "--distortion", str(model), "--points", mode,
           "--panel", f"{PANEL[0]}x{PANEL[1]}", "--source", f"{SOURCE[0]}x{SOURCE[1]}"]
    text = "\n".join(f"{float(a)!r} {float(b)!r}" for a, b in points) + "\n"
    out = subprocess.run(cmd, input=text, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed: {out.stderr}")
    rows = [[float(v) for v in line.split()] for line in out.stdout.splitlines()]
    return np.array(rows, dtype=np.float64).reshape(len(points), 3, 2)


def project(name, xy):
    k, d = channel(name)
    obj = np.hstack([xy, np.ones((len(xy), 1))]).reshape(-1, 1, 3)
    img, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), k, d)
    return img.reshape(-1, 2)


def undistort_converged(points, k, d, criteria):
    """OpenCV 4's undistortPointsIter; OpenCV 5 folded it into undistortPoints."""
    if hasattr(cv2, "undistortPointsIter"):
        return cv2.undistortPointsIter(points, k, d, None, None, criteria)
    return cv2.undistortPoints(points, k, d, R=None, P=None, criteria=criteria)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--binary", default=str(ROOT / "target/debug/dioptra"))
    args = ap.parse_args()
    failures = []

    def check(what, err):
        worst = float(np.nanmax(err))
        ok = worst <= TOLERANCE_PX
        print(f"{'ok  ' if ok else 'FAIL'} {what}: largest difference {worst:.2e} px")
        if not ok:
            failures.append(what)

    with tempfile.TemporaryDirectory() as tmp:
        model = Path(tmp) / "eyepiece.toml"
        write_model(model)

        # Directions over the field: a grid out to 50 degrees across and 35 down.
        gx, gy = np.meshgrid(np.linspace(-1.19, 1.19, 41), np.linspace(-0.70, 0.70, 25))
        dirs = np.stack([gx.ravel(), gy.ravel()], axis=1)
        ours = dioptra(args.binary, model, "project", dirs)
        for c, name in enumerate(CHANNELS):
            check(f"project, {name}", np.abs(ours[:, c] - project(name, dirs)).max(axis=1))

        # Panel pixels over the whole panel, corners included.
        px, py = np.meshgrid(np.linspace(-0.5, PANEL[0] - 0.5, 33),
                             np.linspace(-0.5, PANEL[1] - 0.5, 19))
        pix = np.stack([px.ravel(), py.ravel()], axis=1)
        ours = dioptra(args.binary, model, "unproject", pix)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
        for c, name in enumerate(CHANNELS):
            k, d = channel(name)
            theirs = undistort_converged(pix.reshape(-1, 1, 2), k, d, criteria).reshape(-1, 2)
            five = cv2.undistortPoints(pix.reshape(-1, 1, 2), k, d).reshape(-1, 2)
            fx = k[0, 0]
            found = ~np.isnan(ours[:, c, 0])
            if found.sum() < 0.9 * len(pix):
                failures.append(f"unproject, {name}: only {found.sum()} of {len(pix)} inverted")
            check(f"unproject, {name} (against undistortPoints, converged)",
                  fx * np.abs(ours[found, c] - theirs[found]).max(axis=1))
            # Each found direction projects back onto its pixel through OpenCV's model.
            check(f"unproject, {name} (reprojected by projectPoints)",
                  np.abs(project(name, ours[found, c]) - pix[found]).max(axis=1))
            print(f"     (plain undistortPoints, 5 iterations: "
                  f"{fx * np.abs(five[found] - theirs[found]).max():.2e} px off)")

        # The mesh as drawn: panel pixels between the vertices too.
        px, py = np.meshgrid(np.linspace(3.3, PANEL[0] - 4.1, 57),
                             np.linspace(2.7, PANEL[1] - 3.9, 31))
        pix = np.stack([px.ravel(), py.ravel()], axis=1)
        ours = dioptra(args.binary, model, "warp", pix)
        sx, sy = SOURCE[0] / PANEL[0], SOURCE[1] / PANEL[1]
        for c, name in enumerate(CHANNELS):
            drawn = ~np.isnan(ours[:, c, 0])
            src = ours[drawn, c]
            # Source pixel -> render pixel (panel units) -> direction.
            rx = (src[:, 0] + 0.5) / sx - 0.5
            ry = (src[:, 1] + 0.5) / sy - 0.5
            dirs = np.stack([(rx - RENDER["cx"]) / RENDER["fx"],
                             (ry - RENDER["cy"]) / RENDER["fy"]], axis=1)
            check(f"warp mesh, {name} ({drawn.sum()} of {len(pix)} pixels drawn)",
                  np.abs(project(name, dirs) - pix[drawn]).max(axis=1))

    if failures:
        print("FAILED: " + "; ".join(failures))
        sys.exit(1)
    print("dioptra's eyepiece model and pre-warp agree with OpenCV within "
          f"{TOLERANCE_PX} px")


if __name__ == "__main__":
    main()

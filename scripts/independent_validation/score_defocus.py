#!/usr/bin/env python3
"""Scores dioptra's defocus methods (varifocal images) on the independent validation set.

Each method's image comes from `dioptra render` on the scene's pinhole RGB-D at each focus of
the Mitsuba thin-lens stack (generate.py); scored against that truth as score.py scores the
multifocal methods: PSNR on sRGB-encoded images clipped to [0, 1], mean over the foci.

  python3 scripts/independent_validation/score_defocus.py --set ival \\
      --binary target/release/dioptra [--methods gather,lightfield:12,lightfield:36,refine]
      [--out defocus_scores.md]

A method is `gather`, `pyramid` (bounded cost per pixel), `lightfield:N` (N views), `refine`
(C1R with the shipped weights), `refine=FILE` (C1R with other weights) or `foveated` (the
pyramid foveated around the image centre, 5 degrees at full resolution: `dioptra render` has
no gaze option, so it runs the render crate's `foveated_render` example, built with
`cargo build --release -p dioptra-render --example foveated_render`, named by --foveated).

With `--fovea-deg R`, every method is also scored in the fovea (pixels within R degrees of the
centre) and the periphery (the rest) separately: columns `M fovea` and `M periphery`.

  python3 scripts/independent_validation/score_defocus.py --set ival512 \\
      --binary target/release/dioptra --methods gather,pyramid,foveated \\
      --foveated target/release/examples/foveated_render --fovea-deg 5
"""
import argparse
import os
import subprocess
import tempfile

import numpy as np

from score import FOV_DEG, psnr, read, scenes, srgb, write_table


def region_psnr(a, b, mask):
    """PSNR (as score.psnr: sRGB-encoded, clipped) over the pixels of `mask` only."""
    mse = np.mean(((srgb(a) - srgb(b)) ** 2)[mask])
    return 10 * np.log10(1 / max(mse, 1e-20))


def fovea_mask(h, w, radius_deg):
    """Pixels whose centre's direction is within `radius_deg` of the image centre's (a
    pinhole of FOV_DEG across the width)."""
    f = 0.5 * w / np.tan(np.radians(FOV_DEG / 2))
    y, x = np.mgrid[0:h, 0:w]
    r = np.hypot(x + 0.5 - w / 2, y + 0.5 - h / 2)
    return np.degrees(np.arctan2(r, f)) <= radius_deg


def render_args(method):
    if method.startswith("lightfield:"):
        return ["--method", "lightfield", "--views", method.split(":", 1)[1]]
    if method.startswith("refine="):
        return ["--method", "refine", "--weights", method.split("=", 1)[1]]
    return ["--method", method]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", required=True)
    ap.add_argument("--binary", required=True)
    ap.add_argument("--methods", default="gather,lightfield:12,lightfield:36,refine")
    ap.add_argument("--foveated", default=None,
                    help="the foveated_render example binary, for --methods foveated")
    ap.add_argument("--fovea-deg", type=float, default=None,
                    help="also score the fovea (this radius, degrees) and the periphery")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    methods = a.methods.split(",")
    if "foveated" in methods and not a.foveated:
        ap.error("--methods foveated needs --foveated (the foveated_render example binary)")
    columns = []
    for m in methods:
        columns += [m] + ([f"{m} fovea", f"{m} periphery"] if a.fovea_deg else [])
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, scene, foci, truth in scenes(a.set):
            row = [name]
            color, depth = os.path.join(scene, "color.pfm"), os.path.join(scene, "depth.pfm")
            for m in methods:
                scores = []
                for q, t in zip(foci, truth):
                    out = os.path.join(tmp, "out.pfm")
                    if m == "foveated":
                        h, w = t.shape[:2]
                        cmd = [a.foveated, color, depth, q, str(w / 2), str(h / 2), out]
                    else:
                        cmd = [a.binary, "render", "--color", color, "--depth", depth,
                               "--focus", q, "--backend", "cpu", "--out", out] + render_args(m)
                    r = subprocess.run(cmd, capture_output=True, text=True)
                    if r.returncode != 0:
                        print(f"{name} {m} {q} D: failed: {r.stderr.strip()[-300:]}", flush=True)
                        scores.append([float("nan")] * (3 if a.fovea_deg else 1))
                        continue
                    img = read(out)
                    s = [psnr(img, t)]
                    if a.fovea_deg:
                        fov = fovea_mask(t.shape[0], t.shape[1], a.fovea_deg)
                        s += [region_psnr(img, t, fov), region_psnr(img, t, ~fov)]
                    scores.append(s)
                row += [float(v) for v in np.mean(np.array(scores), axis=0)]
            rows.append(row)
            print(" | ".join([row[0]] + [f"{v:.2f}" for v in row[1:]]), flush=True)
    write_table(rows, columns, a.out)


if __name__ == "__main__":
    main()

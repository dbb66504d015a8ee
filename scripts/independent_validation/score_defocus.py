#!/usr/bin/env python3
"""Scores dioptra's defocus methods (varifocal images) on the independent validation set.

Each method's image comes from `dioptra render` on the scene's pinhole RGB-D at each focus of
the Mitsuba thin-lens stack (generate.py); scored against that truth as score.py scores the
multifocal methods: PSNR on sRGB-encoded images clipped to [0, 1], mean over the foci.

  python3 scripts/independent_validation/score_defocus.py --set ival \\
      --binary target/release/dioptra [--methods gather,lightfield:12,lightfield:36,refine]
      [--out defocus_scores.md]

A method is `gather`, `lightfield:N` (N views), `refine` (C1R with the shipped weights) or
`refine=FILE` (C1R with other weights).
"""
import argparse
import os
import subprocess
import tempfile

import numpy as np

from score import psnr, read, scenes, write_table


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
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    methods = a.methods.split(",")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, scene, foci, truth in scenes(a.set):
            row = [name]
            for m in methods:
                scores = []
                for q, t in zip(foci, truth):
                    out = os.path.join(tmp, "out.pfm")
                    cmd = [a.binary, "render", "--color", os.path.join(scene, "color.pfm"),
                           "--depth", os.path.join(scene, "depth.pfm"), "--focus", q,
                           "--backend", "cpu", "--out", out] + render_args(m)
                    r = subprocess.run(cmd, capture_output=True, text=True)
                    if r.returncode != 0:
                        print(f"{name} {m} {q} D: failed: {r.stderr.strip()[-300:]}", flush=True)
                        scores.append(float("nan"))
                        continue
                    scores.append(psnr(read(out), t))
                row.append(float(np.mean(scores)))
            rows.append(row)
            print(" | ".join([row[0]] + [f"{v:.2f}" for v in row[1:]]), flush=True)
    write_table(rows, methods, a.out)


if __name__ == "__main__":
    main()

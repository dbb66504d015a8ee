#!/usr/bin/env python3
"""Scores dioptra's light-field synthesis on the independent light-field set (generate_lf.py).

For every scene, `dioptra lightfield` synthesises the whole grid from 9 (or 5) of its views
(the inputs `--inputs` picks: corners and centre, plus edge centres for 9); each view no input
came from (a novel view) is scored against Mitsuba's own render of it: PSNR on sRGB-encoded
images clipped to [0, 1], mean over the novel views. Beside it, the nearest input view shown
unchanged in place of each novel view (the baseline a light field without synthesis gives).

  python3 scripts/independent_validation/score_lf.py --set ivlf --binary target/release/dioptra
      [--inputs 9,5] [--backend cpu|gpu] [--out lf_scores.md]
  python3 scripts/independent_validation/score_lf.py --set ivlf --binary target/release/dioptra
      --foveate 2 [--fill across|within] [--inputs 9] [--out fv_scores.md]
  python3 scripts/independent_validation/score_lf.py --set ivlf --binary target/release/dioptra
      --method refine --weights c5r.safetensors [--inputs 9]

With --method refine, each light field is also synthesised with `dioptra lightfield --method
refine --weights PATH` (a C5R net on the classical views) and scored beside the classical one;
the table adds, per input count, the refined PSNR and the worst novel view's change against
classical (refined minus classical, dB), and says whether any scene's mean or any view fell
below classical.

With --foveate S, `dioptra lightfield --foveate S` keeps each synthesised view's log-polar
samples around the image centre and fills the rest (--fill across: every view's samples
reprojected into each view by their depth, then interpolated, the default; within: each view
from its own samples, the paper's interpolation); the table then gives, per region
(fovea: the disk of diameter 0.1 image diagonal around the gaze; periphery 1 the ring out to
0.4; periphery 2 out to 1), the PSNR of the full and of the foveated synthesis against the
truth (of the mean squared error over the novel views), and the fraction of rays kept.
"""
import argparse
import glob
import json
import math
import os
import re
import subprocess
import tempfile

import mitsuba as mi
import numpy as np

from score import read as read_pfm, srgb  # the multifocal scorer's PFM reader and sRGB encoding

mi.set_variant("scalar_rgb")


def read_png_srgb(path):
    """An 8-bit PNG's sRGB-encoded values in [0, 1]."""
    a = np.array(mi.Bitmap(path), dtype=np.float64)[..., :3]
    return a / 255.0


def psnr(a, b):
    """PSNR of two sRGB-encoded images in [0, 1]."""
    mse = float(np.mean((a - b) ** 2))
    return 100.0 if mse == 0 else 10 * np.log10(1.0 / mse)


def picks(n, inputs):
    """The input views `dioptra lightfield --inputs` takes from an n x n grid."""
    m, e = n // 2, n - 1
    if inputs == 5:
        return [(0, 0), (0, e), (m, m), (e, 0), (e, e)]
    if inputs == 9:
        return [(0, 0), (0, m), (0, e), (m, 0), (m, m), (m, e), (e, 0), (e, m), (e, e)]
    raise SystemExit(f"--inputs takes 5 or 9, not {inputs}")


def synthesise(a, scene, meta, inputs, out, extra=()):
    """`dioptra lightfield` on `scene` from `inputs` of its views into `out`; its run."""
    cmd = [a.binary, "lightfield", "--views", scene, "--inputs", str(inputs),
           "--span", str(meta["span_m"]), "--grid", str(meta["grid"]),
           "--fov-deg", str(meta["fov_deg"]), "--backend", a.backend, "--out", out, *extra]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{res.stderr}")
    return res


REGIONS = [("fovea", 0.0, 0.1), ("periphery 1", 0.1, 0.4), ("periphery 2", 0.4, 1.0)]


def region_masks(h, w):
    """Rings around the image centre, diameters as fractions of the image diagonal."""
    diag = math.hypot(w, h)
    yy, xx = np.mgrid[0:h, 0:w]
    r = np.hypot(xx + 0.5 - w / 2, yy + 0.5 - h / 2)
    return [((r > 0.5 * a * diag) | (a == 0)) & (r <= 0.5 * b * diag) for _, a, b in REGIONS]


def foveated(a, scenes):
    k = int(a.inputs.split(",")[0])
    cols = [f"full: {n}" for n, _, _ in REGIONS] + [f"S={a.foveate:g}: {n}" for n, _, _ in REGIONS] + ["rays kept %"]
    rows = []
    for d in scenes:
        meta = json.load(open(os.path.join(d, "lightfield.json")))
        n = meta["grid"]
        novel = [(r, c) for r in range(n) for c in range(n) if (r, c) not in picks(n, k)]
        err = {}
        frac = None
        for mode in ("full", "fov"):
            with tempfile.TemporaryDirectory() as out:
                extra = ["--foveate", str(a.foveate), "--foveate-fill", a.fill] if mode == "fov" else []
                res = synthesise(a, d, meta, k, out, extra)
                if mode == "fov":
                    frac = float(re.search(r"([0-9.]+) % of the rays kept", res.stdout).group(1))
                se = np.zeros(3)
                cnt = np.zeros(3)
                for (r, c) in novel:
                    t = srgb(read_pfm(os.path.join(d, f"view_{r:02}_{c:02}.pfm")))
                    y = read_png_srgb(os.path.join(out, f"view_{r:02}_{c:02}.png"))
                    for i, m in enumerate(region_masks(*t.shape[:2])):
                        se[i] += float(np.sum((y[m] - t[m]) ** 2))
                        cnt[i] += m.sum() * 3
                err[mode] = [10 * np.log10(1.0 / (se[i] / cnt[i])) for i in range(3)]
        rows.append((os.path.basename(d), err["full"] + err["fov"] + [frac]))
        print(os.path.basename(d), " ".join(f"{v:.2f}" for v in rows[-1][1]), flush=True)
    return cols, rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", required=True, help="directory made by generate_lf.py")
    ap.add_argument("--binary", required=True, help="the dioptra binary")
    ap.add_argument("--inputs", default="9,5", help="input view counts, comma-separated")
    ap.add_argument("--backend", default="cpu", help="dioptra's backend: cpu or gpu")
    ap.add_argument("--foveate", type=float, help="log-buffer scale S: score foveated synthesis")
    ap.add_argument("--fill", default="across", choices=["across", "within"],
                    help="with --foveate: fill unsampled rays across views or within each view")
    ap.add_argument("--method", default="classical", choices=["classical", "refine"],
                    help="refine: score a C5R net's refinement beside the classical synthesis")
    ap.add_argument("--weights", help="C5R weights for --method refine")
    ap.add_argument("--out", help="write the table here (markdown) as well as printing it")
    a = ap.parse_args()
    if (a.method == "refine") != (a.weights is not None):
        raise SystemExit("--method refine takes --weights PATH (and --weights needs --method refine)")
    if a.method == "refine" and a.foveate is not None:
        raise SystemExit("--method refine scores the full synthesis: leave out --foveate")
    refine = ["--method", "refine", "--weights", a.weights] if a.weights else None
    counts = [int(k) for k in a.inputs.split(",")]
    scenes = sorted(os.path.dirname(p) for p in glob.glob(os.path.join(a.set, "*", "lightfield.json")))
    if not scenes:
        raise SystemExit(f"no scenes (*/lightfield.json) under {a.set}: run generate_lf.py first")
    if a.foveate is not None:
        cols, rows = foveated(a, scenes)
        lines = ["| scene | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
        for name, row in rows:
            lines.append(f"| {name} | " + " | ".join(f"{v:.2f}" for v in row) + " |")
        mean = np.mean([r for _, r in rows], axis=0)
        lines.append("| **mean** | " + " | ".join(f"**{v:.2f}**" for v in mean) + " |")
        table = "\n".join(lines)
        print(table)
        if a.out:
            with open(a.out, "w") as f:
                f.write(table + "\n")
        return
    cols = [c for k in counts for c in (f"nearest input ({k})", f"classical ({k} inputs)")
            + ((f"refine ({k} inputs)", f"worst view refine - classical ({k})") if refine else ())]
    rows, times = [], {k: [] for k in counts}
    rtimes = {k: [] for k in counts}
    for d in scenes:
        meta = json.load(open(os.path.join(d, "lightfield.json")))
        n = meta["grid"]
        truth = {(r, c): srgb(read_pfm(os.path.join(d, f"view_{r:02}_{c:02}.pfm")))
                 for r in range(n) for c in range(n)}
        row = []
        for k in counts:
            ins = picks(n, k)
            novel = [v for v in truth if v not in ins]
            near = []
            for (r, c) in novel:
                nr, nc = min(ins, key=lambda p: (p[0] - r) ** 2 + (p[1] - c) ** 2)
                shown = read_png_srgb(os.path.join(d, f"view_{nr:02}_{nc:02}.png"))
                near.append(psnr(shown, truth[(r, c)]))
            syn, ref = [], []
            for extra, scores, ts in ((), syn, times[k]), (refine, ref, rtimes[k]):
                if extra is None:
                    continue
                with tempfile.TemporaryDirectory() as out:
                    res = synthesise(a, d, meta, k, out, extra)
                    ms = re.search(r"in (\d+) ms", res.stdout)
                    if ms:
                        ts.append(float(ms.group(1)))
                    scores += [psnr(read_png_srgb(os.path.join(out, f"view_{r:02}_{c:02}.png")),
                                    truth[(r, c)]) for (r, c) in novel]
            row += [float(np.mean(near)), float(np.mean(syn))]
            if refine:
                row += [float(np.mean(ref)), float(min(np.subtract(ref, syn)))]
        rows.append((os.path.basename(d), row))
        print(os.path.basename(d), " ".join(f"{v:.2f}" for v in row), flush=True)
    lines = ["| scene | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for name, row in rows:
        lines.append(f"| {name} | " + " | ".join(f"{v:.2f}" for v in row) + " |")
    mean = np.mean([r for _, r in rows], axis=0)
    lines.append("| **mean** | " + " | ".join(f"**{v:.2f}**" for v in mean) + " |")
    for k in counts:
        for method, ts in (("classical", times[k]), ("refine", rtimes[k])):
            if ts:
                lines.append("")
                lines.append(f"{k} inputs, {method}: {np.median(ts):.0f} ms median per light field "
                             f"(`dioptra lightfield --method {method} --backend {a.backend}`, "
                             f"{n} x {n} views of {meta['size']} px)")
    if refine:
        # Per input count: columns classical, refine, worst view at 4i + 1, 4i + 2, 4i + 3.
        for i, k in enumerate(counts):
            below = [name for name, r in rows if r[4 * i + 2] < r[4 * i + 1]]
            worst = min(r[4 * i + 3] for _, r in rows)
            lines.append("")
            lines.append(f"{k} inputs: refine below classical on {len(below)} of {len(rows)} scenes' "
                         f"means{' (' + ', '.join(below) + ')' if below else ''}; worst novel view "
                         f"{worst:+.2f} dB ({a.weights})")
    table = "\n".join(lines)
    print(table)
    if a.out:
        with open(a.out, "w") as f:
            f.write(table + "\n")


if __name__ == "__main__":
    main()

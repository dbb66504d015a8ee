#!/usr/bin/env python3
"""Scores dioptra's multifocal methods on the independent validation set (generate.py).

Each method's layers come from `dioptra decompose` on the scene's pinhole RGB-D; what the eye
sees of them is computed here by a retina written independently of crates/render's: each layer
convolved with a uniform disk (supersampled pixel coverage) of angular diameter
pupil * |plane - focus| and summed, the image edge-replicated; scored against the Mitsuba
thin-lens truth at every focus of the stack, PSNR on sRGB-encoded images clipped to [0, 1].

  python3 scripts/independent_validation/score.py --set ival --binary target/release/dioptra
      [--methods linear,spectral,optimized,refine] [--weights C4R.safetensors] [--variant LABEL='ARGS' ...]
      [--fovea-deg R] [--out scores.md]

A variant is one more column: `decompose` with ARGS (shell words) instead of `--method M`, e.g.
--variant "spectral gather 8=--method spectral --target-method gather --focal-samples 8";
`{scene}` in ARGS is the scene's directory (`--targets {scene}/stack` fits the truth itself: an
oracle no rig has, scored at the foci it fitted).

--fovea-deg R adds, per method, the same score inside a disk of R degrees around the image
centre (the gaze `decompose --method hybrid` assumes): a column "M fovea" beside each "M".
"""
import argparse
import glob
import math
import os
import re
import shlex
import subprocess
import tempfile

import mitsuba as mi
import numpy as np

mi.set_variant("scalar_rgb")

FOV_DEG = 20.0
PUPIL_M = 0.004
PLANES = [0.2, 0.8, 1.4, 2.0]


def read(path):
    if path.endswith(".pfm"):
        with open(path, "rb") as f:
            magic = f.readline().strip()
            w, h = map(int, f.readline().split())
            scale = float(f.readline())
            c = 3 if magic == b"PF" else 1
            a = np.frombuffer(f.read(), dtype="<f4" if scale < 0 else ">f4").reshape(h, w, c)
            return a[::-1].astype(np.float64)
    a = np.array(mi.Bitmap(path), dtype=np.float64)
    return a[..., :3] if a.ndim == 3 else a[..., None]


def disk(diameter, sub=16):
    """A disk of `diameter` pixels: each tap the fraction of its pixel inside (sub x sub)."""
    r = diameter / 2
    if r < 0.5 / sub:
        return np.ones((1, 1))
    n = int(math.ceil(r - 0.5))
    off = (np.arange(sub) + 0.5) / sub - 0.5
    ax = np.arange(-n, n + 1)
    px = (ax[:, None] + off[None, :]).reshape(-1)
    xx, yy = np.meshgrid(px, px)
    inside = (xx * xx + yy * yy <= r * r).astype(np.float64)
    k = inside.reshape(2 * n + 1, sub, 2 * n + 1, sub).mean(axis=(1, 3))
    return k / k.sum()


def convolve(img, k):
    n = k.shape[0] // 2
    if n == 0:
        return img * k[0, 0]
    h, w = img.shape[:2]
    p = np.pad(img, ((n, n), (n, n), (0, 0)), mode="edge")
    H, W = p.shape[:2]
    kk = np.zeros((H, W))
    kk[: 2 * n + 1, : 2 * n + 1] = k
    kk = np.roll(kk, (-n, -n), axis=(0, 1))
    F = np.fft.rfft2(kk)
    out = np.stack([np.fft.irfft2(np.fft.rfft2(p[..., c]) * F, s=(H, W)) for c in range(p.shape[2])], -1)
    return out[n : n + h, n : n + w]


def retina(layers, q, width):
    pitch = 2 * math.tan(math.radians(FOV_DEG) / 2) / width
    return sum(convolve(l, disk(PUPIL_M * abs(p - q) / pitch)) for p, l in zip(PLANES, layers))


def srgb(x):
    x = np.clip(x, 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def psnr(a, b, mask=None):
    d = (srgb(a) - srgb(b)) ** 2
    mse = np.mean(d) if mask is None else np.mean(d[mask])
    return 10 * math.log10(1 / max(mse, 1e-20))


def fovea_mask(h, w, deg):
    """Pixels whose centre lies within `deg` degrees of the image centre (the tangent plane's
    angle, FOV_DEG over the width)."""
    pitch = 2 * math.tan(math.radians(FOV_DEG) / 2) / w
    r = math.tan(math.radians(deg)) / pitch
    y, x = np.mgrid[0:h, 0:w]
    return (x + 0.5 - w / 2) ** 2 + (y + 0.5 - h / 2) ** 2 <= r * r


def scenes(set_dir):
    """Each scene of a generate.py set: its name, its directory, its foci as their file names
    write them (e.g. "0.10") and the truth's thin-lens images at them."""
    for d in sorted(glob.glob(os.path.join(set_dir, "*", "color.pfm"))):
        scene = os.path.dirname(d)
        stack = sorted(glob.glob(os.path.join(scene, "stack", "focus_*D.pfm")))
        foci = [re.search(r"focus_([0-9.]+)D", s).group(1) for s in stack]
        yield os.path.basename(scene), scene, foci, [read(s) for s in stack]


def write_table(rows, methods, out):
    """Prints the scores (rows of [scene, score per method]) as a markdown table with the
    mean over scenes, and writes it to `out` if given."""
    lines = ["| scene | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
    for r in rows:
        lines.append("| " + r[0] + " | " + " | ".join(f"{v:.2f}" for v in r[1:]) + " |")
    means = [np.nanmean([r[1 + i] for r in rows]) for i in range(len(methods))]
    lines.append("| **mean** | " + " | ".join(f"**{v:.2f}**" for v in means) + " |")
    text = "\n".join(lines)
    print(text)
    if out:
        with open(out, "w") as f:
            f.write(text + "\n")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", required=True)
    ap.add_argument("--binary", required=True)
    ap.add_argument("--methods", default="linear,spectral,optimized,refine")
    ap.add_argument("--variant", action="append", default=[],
                    help="LABEL=ARGS: a column from `decompose ARGS` (ARGS as shell words)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--fovea-deg", type=float, default=0.0,
                    help="also score inside this many degrees of the image centre")
    ap.add_argument("--weights", default=None,
                    help="the C4R weights `refine` runs (default: the binary's shipped c4r)")
    a = ap.parse_args()
    runs = [(m, ["--method", m]) for m in a.methods.split(",") if m]
    for v in a.variant:
        label, sep, args = v.partition("=")
        if not sep or not label.strip():
            ap.error(f"--variant {v!r}: expected LABEL=ARGS")
        runs.append((label.strip(), shlex.split(args)))
    methods = [m for m, _ in runs]
    if a.fovea_deg > 0:
        methods = [c for m in methods for c in (m, m + " fovea")]
    rows = []
    # The layers go to a temporary directory, not the set's scene folders: scorers running
    # at once on one set would overwrite each other's.
    with tempfile.TemporaryDirectory() as tmp:
        for name, scene, foci, truth in scenes(a.set):
            foci = [float(q) for q in foci]
            width = truth[0].shape[1]
            row = [name]
            for m, args in runs:
                out = os.path.join(tmp, name, "layers_" + re.sub(r"[^A-Za-z0-9.-]+", "_", m))
                cmd = [a.binary, "decompose", "--color", os.path.join(scene, "color.pfm"),
                       "--depth", os.path.join(scene, "depth.pfm"),
                       *[x.replace("{scene}", scene) for x in args],
                       "--backend", "cpu", "--out", out]
                if m == "refine" and a.weights:
                    cmd += ["--weights", a.weights]
                r = subprocess.run(cmd, capture_output=True, text=True)
                if r.returncode != 0:
                    row += [float("nan")] * (2 if a.fovea_deg > 0 else 1)
                    print(f"{name} {m}: failed: {r.stderr.strip()[-300:]}", flush=True)
                    continue
                layers = [read(os.path.join(out, f"layer_{p:.2f}D.exr")) for p in PLANES]
                seen = [retina(layers, q, width) for q in foci]
                row.append(np.mean([psnr(s, t) for s, t in zip(seen, truth)]))
                if a.fovea_deg > 0:
                    mask = fovea_mask(truth[0].shape[0], width, a.fovea_deg)
                    row.append(np.mean([psnr(s, t, mask) for s, t in zip(seen, truth)]))
            rows.append(row)
            print(" | ".join([row[0]] + [f"{v:.2f}" for v in row[1:]]), flush=True)
    write_table(rows, methods, a.out)


if __name__ == "__main__":
    main()

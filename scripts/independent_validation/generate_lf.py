#!/usr/bin/env python3
"""Independent light-field validation set for dioptra's light-field synthesis (issue 41).

Renders, with Mitsuba 3 (`pip install mitsuba`, scalar_rgb: CPU only) and not with dioptra-sim,
the twelve scenes of generate.py as dense light fields: a `grid` x `grid` square of pinhole
views, `span` metres across, each looking straight ahead (dioptra's 20 degree field). Per scene
directory, in the layout `dioptra lightfield --views DIR` reads:
  view_<r>_<c>.png        the view's colour, 8-bit sRGB (what a rig's camera gives)
  view_<r>_<c>_depth.exr  its z-depth at each pixel centre, metres
  view_<r>_<c>.pfm        its colour in linear float: the truth a synthesised view is scored on
  lightfield.json         size, grid, span (metres), field of view, samples per pixel
Row r runs down the image and column c to its right, as in `dioptra sim scene`: view (r, c) is
at ((c - (grid - 1) / 2) step, (r - (grid - 1) / 2) step) with step = span / (grid - 1), x to
the image's right and y down it. Mitsuba's camera has x to the image's left and y up, so its
origin is the negated position.

  python3 scripts/independent_validation/generate_lf.py --out ivlf [--size 128] [--grid 9]
      [--span 0.01] [--spp 16] [--scenes all]
"""
import argparse
import json
import math
import os
import sys

import mitsuba as mi
import numpy as np

mi.set_variant("scalar_rgb")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from generate import FOV_DEG, scenes  # noqa: E402  (the same scenes as the multifocal set)


def view_sensor(size, spp, position):
    """A pinhole at dioptra's `position` (metres; x right, y down), looking along +z; `spp`
    jittered samples per pixel, or 0 for one sample at each pixel's centre."""
    x, y = -position[0], -position[1]
    look = mi.ScalarTransform4f().look_at(origin=[x, y, 0], target=[x, y, 1], up=[0, 1, 0])
    film = {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"},
            "pixel_format": "rgb"}
    return {"type": "perspective", "fov": FOV_DEG, "fov_axis": "x", "to_world": look,
            "film": film,
            "sampler": {"type": "multijitter", "sample_count": spp} if spp > 0
            else {"type": "stratified", "sample_count": 1, "jitter": False}}


def render(shapes, sens, aovs):
    d = {"type": "scene", "integrator": {"type": "aov", "aovs": aovs}, "sensor": sens}
    d.update(shapes)
    return np.array(mi.render(mi.load_dict(d)), dtype=np.float32)


def write_pfm(path, a):
    a = np.asarray(a, dtype=np.float32)
    h, w = a.shape[:2]
    with open(path, "wb") as f:
        f.write(b"PF\n" if a.ndim == 3 else b"Pf\n")
        f.write(f"{w} {h}\n-1.0\n".encode())
        f.write(np.ascontiguousarray(a[::-1]).astype("<f4").tobytes())


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--size", type=int, default=128, help="pixels per side of a view")
    ap.add_argument("--grid", type=int, default=9, help="views per side of the light field")
    ap.add_argument("--span", type=float, default=0.01, help="side of the views' square, metres")
    ap.add_argument("--spp", type=int, default=16, help="samples per pixel (antialiasing)")
    ap.add_argument("--scenes", default="all", help="comma-separated names, or all")
    a = ap.parse_args()
    if a.grid < 2:
        ap.error("--grid must be at least 2")
    all_scenes = scenes()
    names = list(all_scenes) if a.scenes == "all" else a.scenes.split(",")
    unknown = [n for n in names if n not in all_scenes]
    if unknown:
        ap.error(f"unknown scenes {unknown}: expected some of {list(all_scenes)}")
    step = a.span / (a.grid - 1)
    half = (a.grid - 1) / 2
    # z-depth from the distance along each pixel's ray.
    t = math.tan(math.radians(FOV_DEG) / 2)
    c = (np.arange(a.size) + 0.5) / a.size * 2 - 1
    xx, yy = np.meshgrid(c * t, c * t)
    ray = np.sqrt(1 + xx * xx + yy * yy)
    for name in names:
        d = os.path.join(a.out, name)
        os.makedirs(d, exist_ok=True)
        zmin, zmax = math.inf, 0.0
        for r in range(a.grid):
            for col in range(a.grid):
                pos = ((col - half) * step, (r - half) * step)
                color = render(all_scenes[name], view_sensor(a.size, a.spp, pos), "a:albedo")[..., :3]
                # Depth along each pixel centre's ray, as a renderer's depth buffer holds it (an
                # average over the pixel would put edge pixels between the two surfaces).
                dist = render(all_scenes[name], view_sensor(a.size, 0, pos), "t:depth")[..., 0]
                z = (dist / ray).astype(np.float32)
                z[~np.isfinite(z) | (z <= 0)] = 100.0
                zmin, zmax = min(zmin, z.min()), max(zmax, z.max())
                base = os.path.join(d, f"view_{r:02}_{col:02}")
                write_pfm(base + ".pfm", color)
                mi.Bitmap(np.ascontiguousarray(color)).convert(
                    mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True
                ).write(base + ".png")
                mi.Bitmap(np.ascontiguousarray(z[..., None])).write(base + "_depth.exr")
        with open(os.path.join(d, "lightfield.json"), "w") as f:
            json.dump({"size": a.size, "grid": a.grid, "span_m": a.span, "fov_deg": FOV_DEG,
                       "spp": a.spp}, f)
        print(f"{name}: {a.grid}x{a.grid} views over {a.span * 1e3:.1f} mm, depth "
              f"{1 / zmax:.2f} to {1 / zmin:.2f} D", flush=True)


if __name__ == "__main__":
    main()

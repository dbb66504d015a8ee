#!/usr/bin/env python3
"""Independent validation set for dioptra's multifocal methods (issue 42).

Renders, with Mitsuba 3 (`pip install mitsuba`, the scalar_rgb variant: CPU only) and not with
dioptra-sim, a dozen scenes unlike dioptra's training family (slanted and curved smooth
surfaces, spheres, large textured planes, thin structures, mixed scales), each as:
  color.pfm   pinhole RGB (linear), the input a rig gets
  depth.pfm   pinhole z-depth, metres
  stack/focus_<q>D.pfm   thin-lens renders (4 mm pupil) focused at q diopters: the truth
The eye is dioptra's default: 20 degrees horizontal over the image width. Images are the
unlit surface colour (Mitsuba's `aov` integrator, albedo at the first hit), so the truth's only
noise is the lens sampling, as in dioptra-sim's thin lens.

  python3 scripts/independent_validation/generate.py --out ival [--size 96] [--spp 64]
      [--foci 8] [--scenes all]
"""
import argparse
import math
import os

import mitsuba as mi
import numpy as np

mi.set_variant("scalar_rgb")

FOV_DEG = 20.0
PUPIL_M = 0.004


def checker(c0, c1, scale):
    return {
        "type": "checkerboard",
        "color0": {"type": "rgb", "value": c0},
        "color1": {"type": "rgb", "value": c1},
        "to_uv": mi.ScalarTransform4f().scale([scale, scale, 1.0]),
    }


def diffuse(tex):
    return {"type": "diffuse", "reflectance": tex}


def rgb(c):
    return diffuse({"type": "rgb", "value": c})


def wall(dist, tex, size=6.0):
    """A fronto-parallel rectangle `dist` metres away, `size` metres across."""
    return {
        "type": "rectangle",
        "to_world": mi.ScalarTransform4f().translate([0, 0, dist]).scale([size, size, 1.0]),
        "bsdf": diffuse(tex),
    }


def sphere(x, y, z, r, bsdf):
    return {"type": "sphere", "center": [x, y, z], "radius": r, "bsdf": bsdf}


def scenes():
    """Name -> dict of shapes. The camera is at the origin looking along +z."""
    out = {}
    # 1. A slanted textured plane from 0.3 m to 5 m (about 3.3 to 0.2 D): a smooth ramp.
    out["slanted-plane"] = {
        "plane": {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f().translate([0, -0.05, 1.6]).rotate([1, 0, 0], 80).scale([0.6, 2.0, 1]),
            "bsdf": diffuse(checker([0.9, 0.8, 0.2], [0.1, 0.2, 0.6], 12)),
        },
        "wall": wall(8.0, checker([0.6, 0.6, 0.6], [0.2, 0.2, 0.2], 20)),
    }
    # 2. Spheres at several depths before a wall.
    s = {"wall": wall(5.0, checker([0.8, 0.3, 0.3], [0.3, 0.3, 0.8], 30))}
    for i, (x, y, z, r) in enumerate([(-0.08, 0.02, 0.45, 0.04), (0.05, -0.03, 0.8, 0.07), (0.0, 0.06, 1.6, 0.1), (-0.12, -0.1, 2.5, 0.2)]):
        s[f"s{i}"] = sphere(x, y, z, r, diffuse(checker([0.9, 0.9, 0.9], [0.1 * i, 0.5, 0.2], 8)))
    out["spheres"] = s
    # 3. A large curved surface close up: one big sphere filling most of the view.
    out["big-sphere"] = {
        "s": sphere(0.0, 0.0, 1.2, 0.6, diffuse(checker([0.2, 0.7, 0.3], [0.9, 0.9, 0.8], 24))),
        "wall": wall(6.0, checker([0.5, 0.5, 0.9], [0.1, 0.1, 0.1], 40)),
    }
    # 4. Thin structures: a fence of thin cylinders at 0.5 m before a textured wall at 3 m.
    f = {"wall": wall(3.0, checker([0.9, 0.6, 0.2], [0.2, 0.4, 0.1], 40))}
    for i in range(7):
        x = -0.09 + 0.03 * i
        f[f"rod{i}"] = {
            "type": "cylinder", "p0": [x, -0.3, 0.5], "p1": [x, 0.3, 0.5], "radius": 0.0015,
            "bsdf": rgb([0.95, 0.95, 0.95]),
        }
    out["fence"] = f
    # 5. Stepped boxes (mixed scales) at 0.4, 0.7, 1.2 and 2 m.
    b = {"wall": wall(4.0, checker([0.7, 0.7, 0.2], [0.2, 0.2, 0.5], 16))}
    for i, (x, z, sz) in enumerate([(-0.1, 0.4, 0.03), (-0.02, 0.7, 0.06), (0.08, 1.2, 0.1), (0.2, 2.0, 0.2)]):
        b[f"box{i}"] = {
            "type": "cube",
            "to_world": mi.ScalarTransform4f().translate([x, 0.0, z]).rotate([0, 1, 0], 25).scale(sz),
            "bsdf": diffuse(checker([0.9, 0.2, 0.2], [0.9, 0.9, 0.9], 4)),
        }
    out["boxes"] = b
    # 6. A floor receding to the horizon with small objects on it.
    out["floor"] = {
        "floor": {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f().translate([0, -0.15, 3.0]).rotate([1, 0, 0], 90).scale([3.0, 3.0, 1]),
            "bsdf": diffuse(checker([0.8, 0.8, 0.8], [0.3, 0.2, 0.1], 60)),
        },
        "a": sphere(-0.05, -0.12, 0.6, 0.03, rgb([0.2, 0.6, 0.9])),
        "b": sphere(0.1, -0.1, 1.5, 0.05, rgb([0.9, 0.5, 0.1])),
        "wall": wall(10.0, checker([0.5, 0.7, 0.9], [0.6, 0.8, 1.0], 10), size=20.0),
    }
    # 7. A striped card tilted about the vertical axis at 0.5 m over a far wall.
    out["tilted-card"] = {
        "card": {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f().translate([0.0, 0.0, 0.5]).rotate([0, 1, 0], 50).scale([0.06, 0.05, 1]),
            "bsdf": diffuse(checker([1.0, 1.0, 1.0], [0.0, 0.0, 0.0], 6)),
        },
        "wall": wall(5.0, checker([0.3, 0.8, 0.5], [0.8, 0.3, 0.6], 25)),
    }
    # 8. A corridor: two side walls converging to a far end wall.
    out["corridor"] = {
        "left": {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f().translate([-0.25, 0, 2.5]).rotate([0, 1, 0], 90).scale([2.5, 0.4, 1]),
            "bsdf": diffuse(checker([0.8, 0.5, 0.3], [0.3, 0.2, 0.1], 20)),
        },
        "right": {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f().translate([0.25, 0, 2.5]).rotate([0, 1, 0], -90).scale([2.5, 0.4, 1]),
            "bsdf": diffuse(checker([0.3, 0.5, 0.8], [0.1, 0.2, 0.3], 20)),
        },
        "end": wall(5.0, checker([0.9, 0.9, 0.2], [0.2, 0.2, 0.2], 8)),
    }
    # 9. A horizontal cylinder (curved) with a checker at 0.8 m.
    out["cylinder"] = {
        "c": {"type": "cylinder", "p0": [-0.3, 0.0, 0.9], "p1": [0.3, 0.0, 0.9], "radius": 0.06,
              "bsdf": diffuse(checker([0.9, 0.2, 0.6], [0.1, 0.8, 0.8], 10))},
        "wall": wall(2.0, checker([0.6, 0.6, 0.6], [0.1, 0.1, 0.1], 50)),
    }
    # 10. A grid of small spheres at alternating depths.
    g = {"wall": wall(6.0, checker([0.4, 0.4, 0.4], [0.7, 0.7, 0.7], 12))}
    for i in range(4):
        for j in range(4):
            z = 0.5 + 0.4 * ((i + j) % 3)
            g[f"g{i}{j}"] = sphere((i - 1.5) * 0.05 * z, (j - 1.5) * 0.05 * z, z, 0.012 * z,
                                   rgb([0.2 + 0.2 * i, 0.9 - 0.2 * j, 0.5]))
    out["sphere-grid"] = g
    # 11. Near and far only: a textured card at 0.3 m covering half the view, wall at 10 m.
    out["near-far"] = {
        "card": {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f().translate([-0.06, 0.0, 0.3]).scale([0.06, 0.2, 1]),
            "bsdf": diffuse(checker([0.9, 0.9, 0.9], [0.4, 0.1, 0.1], 10)),
        },
        "wall": wall(10.0, checker([0.1, 0.5, 0.9], [0.9, 0.9, 0.5], 60), size=20.0),
    }
    # 12. A far textured wall alone (0.15 D): the easy case.
    out["far-wall"] = {"wall": wall(6.7, checker([0.9, 0.4, 0.1], [0.1, 0.4, 0.9], 70))}
    return out


def sensor(size, spp, focus_d=None):
    film = {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"},
            "pixel_format": "rgb"}
    # Stratified samples: the truth's own noise (pixel coverage and lens sampling) stays below
    # the differences it scores.
    sampler = {"type": "multijitter", "sample_count": spp}
    look = mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, 1, 0])
    if focus_d is None:
        return {"type": "perspective", "fov": FOV_DEG, "fov_axis": "x", "to_world": look,
                "film": film, "sampler": sampler}
    return {"type": "thinlens", "fov": FOV_DEG, "fov_axis": "x", "to_world": look,
            "aperture_radius": PUPIL_M / 2, "focus_distance": 1.0 / max(focus_d, 1e-4),
            "film": film, "sampler": sampler}


def render(shapes, sens, aovs):
    d = {"type": "scene", "integrator": {"type": "aov", "aovs": aovs}, "sensor": sens}
    d.update(shapes)
    img = mi.render(mi.load_dict(d))
    return np.array(img, dtype=np.float32)


def write_pfm(path, a):
    a = np.asarray(a, dtype=np.float32)
    color = a.ndim == 3
    h, w = a.shape[:2]
    with open(path, "wb") as f:
        f.write(b"PF\n" if color else b"Pf\n")
        f.write(f"{w} {h}\n-1.0\n".encode())
        f.write(np.ascontiguousarray(a[::-1]).astype("<f4").tobytes())


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--spp", type=int, default=144, help="lens samples per pixel of the truth")
    ap.add_argument("--foci", type=int, default=8, help="thin-lens foci over 0.1 to 2.2 D")
    ap.add_argument("--scenes", default="all", help="comma-separated names, or all")
    a = ap.parse_args()
    all_scenes = scenes()
    names = list(all_scenes) if a.scenes == "all" else a.scenes.split(",")
    foci = [0.1 + (2.2 - 0.1) * k / max(a.foci - 1, 1) for k in range(a.foci)]
    for name in names:
        shapes = all_scenes[name]
        d = os.path.join(a.out, name)
        os.makedirs(os.path.join(d, "stack"), exist_ok=True)
        # Pinhole colour and distance (64 samples per pixel for antialiasing).
        pin = render(shapes, sensor(a.size, 64), "a:albedo,t:depth")
        color, dist = pin[..., :3], pin[..., 3]
        # z-depth from the distance along each pixel's ray.
        t = math.tan(math.radians(FOV_DEG) / 2)
        c = (np.arange(a.size) + 0.5) / a.size * 2 - 1
        xx, yy = np.meshgrid(c * t, c * t)
        z = dist / np.sqrt(1 + xx * xx + yy * yy)
        z[~np.isfinite(z) | (z <= 0)] = 100.0
        write_pfm(os.path.join(d, "color.pfm"), color)
        write_pfm(os.path.join(d, "depth.pfm"), z)
        for q in foci:
            img = render(shapes, sensor(a.size, a.spp, q), "a:albedo")[..., :3]
            write_pfm(os.path.join(d, "stack", f"focus_{q:.2f}D.pfm"), img)
        print(f"{name}: depth {1 / z.max():.2f} to {1 / z.min():.2f} D, {len(foci)} foci", flush=True)


if __name__ == "__main__":
    main()

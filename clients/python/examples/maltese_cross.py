#!/usr/bin/env python3
"""A focus target for accommodation experiments: a Maltese cross on a grey field that
steps in depth (near, far, near, ...), streamed to a dioptra daemon.

    dioptra serve --config rig.toml          # with [content] source = "stream"
    python3 examples/maltese_cross.py --url http://127.0.0.1:7420 --near 0.4 --far 2.0

The cross's depth is the frame's depth at its pixels; the background sits at --background
metres. The lens follows the cross when the subject fixates its hub (on the example rig:
`sim_scenario = "vergence"`); with --manual-focus the script sets the lens to the cross's
depth itself at each step, whatever the eyes do, and hands focus back to gaze at the end.
"""

import argparse
import time

import numpy as np

from dioptra_client import Dioptra


def maltese_cross(w: int, h: int, radius: float) -> np.ndarray:
    """A mask of a Maltese cross: four wedges meeting at a solid hub at the centre (the
    fixation point), ``radius`` pixels long, each wedge 13.5 degrees wide at the hub and
    widening to 45 degrees at the rim.

    The hub is 15 % of the radius (over a degree at the example rig's 96 px and 20 degrees),
    wider than the window the daemon reads the fixation depth from (0.75 degrees around
    the gaze point): an eye fixating the centre is on the cross, not between its arms."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    x -= (w - 1) / 2
    y -= (h - 1) / 2
    r = np.hypot(x, y)
    angle = np.degrees(np.arctan2(y, x)) % 90.0
    # Wedges centred on 0 and 90 degrees (modulo 90: on 0), 45 degrees wide at the rim.
    wedge = np.minimum(angle, 90.0 - angle) < 22.5 * (0.3 + 0.7 * r / max(radius, 1))
    return (wedge | (r < 0.15 * radius)) & (r < radius)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--url", default="http://127.0.0.1:7420")
    ap.add_argument("--token")
    ap.add_argument("--near", type=float, default=0.4, help="cross at its nearest, metres")
    ap.add_argument("--far", type=float, default=2.0, help="cross at its farthest, metres")
    ap.add_argument("--background", type=float, default=3.0, help="background, metres")
    ap.add_argument("--step-s", type=float, default=1.0, help="time at each depth")
    ap.add_argument("--fps", type=float, default=60.0)
    ap.add_argument("--seconds", type=float, default=10.0, help="0: until Ctrl-C")
    ap.add_argument("--manual-focus", action="store_true",
                    help="set the lens to the cross's depth at each step (open loop)")
    args = ap.parse_args()

    with Dioptra(args.url, token=args.token) as d:
        w, h = d.width, d.height
        mask = maltese_cross(w, h, 0.4 * min(w, h))
        color = np.full((h, w, 3), 128, np.uint8)
        color[mask] = 16
        print(f"streaming a {w}x{h} Maltese cross ({'shared memory' if d.uses_ring else 'PUT'})")
        t0 = time.monotonic()
        n, focused = 0, None
        try:
            while args.seconds <= 0 or time.monotonic() - t0 < args.seconds:
                near_phase = int((time.monotonic() - t0) / args.step_s) % 2 == 0
                cross_m = args.near if near_phase else args.far
                depth = np.full((h, w), args.background, np.float32)
                depth[mask] = cross_m
                d.send_rgbd(color, depth, depth_units="m", app_time_ns=time.monotonic_ns())
                if args.manual_focus and focused != cross_m:
                    d.set_focus(1.0 / cross_m)
                    focused = cross_m
                n += 1
                time.sleep(max(0.0, t0 + n / args.fps - time.monotonic()))
        except KeyboardInterrupt:
            pass
        finally:
            if args.manual_focus:
                d.release_focus()
        s = d.status()["content"]
        print(f"sent {n} frames; the daemon shows #{s['on_show_seq']}, received "
              f"{s['received']}, shown {s['shown']}, replaced {s['replaced']}")


if __name__ == "__main__":
    main()

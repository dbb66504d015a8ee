#!/usr/bin/env python3
"""An accommodation experiment session against a dioptra daemon: each trial shows a stimulus
at a depth, waits for the lens to settle there, marks stimulus onset, collects a second of
gaze, and is recorded in a file of its own under the subject and trial number.

    dioptra serve --config crates/cli/examples/rig-sim.toml      # any content source
    python3 clients/python/examples/experiment.py --subject s01 --depths 0.5,2.0,1.0

On a rig with ``[content] source = "stream"`` the stimulus is a Maltese cross at the trial's
depth over a background at 3 m, streamed by this script; with the rig's own content (the
procedural scene, files) the trial's depth is where the lens is set. Either way the lens is
put at the stimulus's depth (manual focus) and handed back to gaze at the end. It prints a line
per trial and, with ``--out``, writes the trials as CSV: the recording, when the lens was seen
settled and the stimulus came on (the daemon's host clock, ns), the time from the focus
command to the first settled read-back this script saw (an upper bound on the lens's settle
time: read-backs come every ``devices.lens.poll_ms``), and the gaze of the second that followed
(samples, valid share, mean pupil, mean vergence).
"""

from __future__ import annotations

import argparse
import csv
import math
import pathlib
import sys
import time
from typing import Dict, List, Optional

import numpy as np

from dioptra_client import Dioptra, DioptraError, GazeEvent, NotSettled

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from maltese_cross import maltese_cross  # noqa: E402  (the example beside this one)


def show_stimulus(d: Dioptra, depth_m: float, background_m: float) -> None:
    """A streaming rig: a Maltese cross at ``depth_m`` metres over the background."""
    w, h = d.width, d.height
    mask = maltese_cross(w, h, 0.4 * min(w, h))
    color = np.full((h, w, 3), 128, np.uint8)
    color[mask] = 16
    depth = np.full((h, w), background_m, np.float32)
    depth[mask] = depth_m
    d.send_rgbd(color, depth, depth_units="m", app_time_ns=time.monotonic_ns())


def collect_gaze(d: Dioptra, seconds: float) -> List[GazeEvent]:
    """The gaze samples of the next ``seconds`` (by their host times)."""
    samples: List[GazeEvent] = []
    with d.events(["gaze"], timeout=max(2.0, seconds)) as ev:
        first = next(ev)
        samples.append(first)
        end_ns = first.host_ns + int(seconds * 1e9)
        for g in ev:
            if g.host_ns >= end_ns:
                break
            samples.append(g)
    return samples


def summarize(samples: List[GazeEvent]) -> Dict[str, Optional[float]]:
    valid = [g for g in samples if g.left.valid and g.right.valid]
    pupils = [p for g in valid for p in (g.left.pupil_mm, g.right.pupil_mm) if p is not None]
    vergence = [g.vergence_d for g in samples if g.vergence_d is not None]
    return {
        "gaze_samples": len(samples),
        "valid_share": len(valid) / len(samples) if samples else None,
        "pupil_mm": float(np.mean(pupils)) if pupils else None,
        "vergence_d": float(np.mean(vergence)) if vergence else None,
    }


def run_trial(d: Dioptra, args, trial: int, depth_m: float, streaming: bool) -> Dict:
    focus_d = 1.0 / depth_m
    path = d.start_recording(name=args.name, subject=args.subject, trial=trial)
    try:
        if streaming:
            show_stimulus(d, depth_m, args.background)
        commanded_ns = d.marker({"event": "focus", "trial": trial, "depth_m": depth_m})
        d.set_focus(focus_d)
        try:
            settled = d.wait_settled(timeout=args.settle_timeout, target_d=focus_d)
            settled_ns, settle_ms = settled.host_ns, (settled.host_ns - commanded_ns) / 1e6
        except NotSettled as e:
            print(f"trial {trial}: {e}", file=sys.stderr)
            settled_ns, settle_ms = None, math.nan
        onset_ns = d.marker({"event": "stimulus_on", "trial": trial, "depth_m": depth_m})
        gaze = collect_gaze(d, args.gaze_s)
        d.marker({"event": "stimulus_off", "trial": trial})
    finally:
        stats = d.stop_recording()
    return {"trial": trial, "depth_m": depth_m, "focus_d": focus_d, "recording": path,
            "messages": stats["messages"], "settled_ns": settled_ns, "settle_ms": settle_ms,
            "onset_ns": onset_ns, **summarize(gaze)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--url", default="http://127.0.0.1:7420",
                    help="the daemon: http://host:port or unix:/path/to.sock")
    ap.add_argument("--token", help="the config's api.token, if it sets one")
    ap.add_argument("--subject", default="s01", help="the subject's code (in file names)")
    ap.add_argument("--name", default="accommodation", help="the experiment's name")
    ap.add_argument("--depths", default="0.5,2.0,1.0,0.33",
                    help="stimulus depths, metres, one trial each, in order")
    ap.add_argument("--background", type=float, default=3.0, help="background, metres")
    ap.add_argument("--gaze-s", type=float, default=1.0, help="gaze collected per trial, s")
    ap.add_argument("--settle-timeout", type=float, default=2.0,
                    help="how long to wait for the lens to settle, s")
    ap.add_argument("--out", type=pathlib.Path, help="write the trials here as CSV")
    args = ap.parse_args(argv)
    depths = [float(x) for x in args.depths.split(",") if x.strip()]
    if not depths or any(not (x > 0 and math.isfinite(x)) for x in depths):
        ap.error("--depths: positive distances in metres, e.g. 0.5,2.0")

    rows = []
    with Dioptra(args.url, token=args.token) as d:
        status = d.status()
        streaming = status["content"]["source"] == "stream"
        lo, hi = status["focus"]["lens_range_d"]
        for x in depths:
            if not lo <= 1.0 / x <= hi:
                ap.error(f"--depths: {x} m is {1.0 / x:.2f} D, outside the lens range "
                         f"{lo}..{hi} D")
        print(f"{len(depths)} trials for {args.subject}; content {status['content']['source']}"
              f"{' (this script streams the stimulus)' if streaming else ''}")
        try:
            for trial, depth_m in enumerate(depths, start=1):
                r = run_trial(d, args, trial, depth_m, streaming)
                rows.append(r)
                pupil = "-" if r["pupil_mm"] is None else f"{r['pupil_mm']:.2f} mm"
                print(f"trial {trial}: {depth_m} m ({r['focus_d']:.2f} D), lens seen settled "
                      f"after {r['settle_ms']:.0f} ms, {r['gaze_samples']} gaze samples, pupil "
                      f"{pupil}; {r['recording']}")
        except DioptraError as e:
            print(f"the daemon refused: {e}", file=sys.stderr)
            return 1
        finally:
            d.release_focus()
    if args.out:
        with open(args.out, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Checks the stream content source end to end with the Python client.

Starts `dioptra serve` on the example simulated rig with `[content] source = "stream"`, then:
1. streams 300 frames at 90 Hz through the shared-memory ring, and checks every frame is
   accounted for (accepted: shown or replaced by a newer one; or refused with a reason);
2. the same through `PUT /frame` (no ring), then 30 frames as PNG files through `PUT /frame`;
3. sends frames the daemon must refuse (wrong size, NaN depth, depth buffer without near/far,
   stale sequence number) and checks each is refused, counted, and the frame on show stays;
4. kills a streaming client with SIGKILL and checks the daemon keeps showing its last frame
   and goes on running;
5. stops the daemon with SIGTERM (exit 0).
It prints the ingest time per frame (client write to the daemon's answer) at the display size,
and the daemon's own "content received" and "content to presented" latency.

    pip install ./clients/python
    cargo build
    python3 clients/python/tests/check_stream.py target/debug/dioptra [cpu|gpu]

The second argument is the daemon's `[render] backend` (default cpu; gpu takes any adapter,
a software one included).
"""

import pathlib
import signal
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

from dioptra_client import FrameRefused
from dioptra_client.daemon import Daemon, rig_config

ROOT = pathlib.Path(__file__).resolve().parents[3]
failures = []


def check(ok, what):
    print(("ok   " if ok else "FAIL ") + what)
    if not ok:
        failures.append(what)


def config(tmp: pathlib.Path, backend: str) -> pathlib.Path:
    return rig_config(tmp / "rig.toml", (ROOT / "crates/cli/examples/rig-sim.toml").read_text(),
                      append=f'[content]\nsource = "stream"\n\n[render]\nbackend = "{backend}"\n')


def frame(d, k):
    """Frame k: a uniform colour and depth that encode k, so frames cannot be confused."""
    color = np.full((d.height, d.width, 3), k % 256, np.uint8)
    depth = np.full((d.height, d.width), 0.25 + (k % 8) * 0.25, np.float32)
    return color, depth


def stream(d, n, hz, encoding="raw"):
    ok, refused, times = [], [], []
    t0 = time.monotonic()
    for k in range(n):
        color, depth = frame(d, k)
        t = time.perf_counter()
        try:
            ok.append(d.send_rgbd(color, depth, depth_units="m", encoding=encoding))
        except FrameRefused as e:
            refused.append(str(e))
        times.append(time.perf_counter() - t)
        time.sleep(max(0.0, t0 + (k + 1) / hz - time.monotonic()))
    return ok, refused, times


def accounted(before, after, sent_ok, what):
    received = after["received"] - before["received"]
    shown = after["shown"] - before["shown"]
    replaced = after["replaced"] - before["replaced"]
    pending = received - shown - replaced
    check(received == sent_ok, f"{what}: the daemon received {received} of {sent_ok} accepted")
    check(pending in (0, 1),
          f"{what}: {shown} shown + {replaced} replaced + {pending} waiting = {received}")


def main():
    binary = sys.argv[1] if len(sys.argv) > 1 else str(ROOT / "target/debug/dioptra")
    backend = sys.argv[2] if len(sys.argv) > 2 else "cpu"
    if backend not in ("cpu", "gpu"):
        sys.exit(f"backend {backend!r}: expected cpu or gpu")
    tmp = pathlib.Path(tempfile.mkdtemp())
    rig = Daemon(binary, config(tmp, backend)).start()
    url = rig.url
    try:
        d = rig.client()
        render = d.status()["render"]
        check(render["backend"] == backend,
              f"the daemon renders on the {render['backend']} ({render.get('adapter')})")
        check(d.uses_ring, f"the client maps the ring ({d.width}x{d.height})")
        before = d.status()["content"]
        ok, refused, times = stream(d, 300, 90.0)
        time.sleep(0.3)
        after = d.status()["content"]
        check(len(ok) + len(refused) == 300 and not refused,
              f"300 frames through the ring: {len(ok)} accepted, {len(refused)} refused")
        check(ok == sorted(ok) and len(set(ok)) == len(ok), "sequence numbers grow")
        accounted(before, after, len(ok), "ring")
        check(after["on_show_seq"] == ok[-1], f"the last frame is on show ({after['on_show_seq']})")
        ms = sorted(t * 1e3 for t in times)
        print(f"     ring ingest at {d.width}x{d.height}: p50 {statistics.median(ms):.2f} ms, "
              f"p99 {ms[int(0.99 * len(ms))]:.2f} ms (client write to the daemon's answer)")

        put = rig.client(use_ring=False)
        check(not put.uses_ring, "a client without the ring uses PUT /frame")
        before = put.status()["content"]
        ok2, refused2, times2 = stream(put, 300, 90.0)
        time.sleep(0.3)
        after = put.status()["content"]
        check(len(ok2) == 300 and not refused2, f"300 frames through PUT: {len(ok2)} accepted")
        accounted(before, after, len(ok2), "PUT")
        ms = sorted(t * 1e3 for t in times2)
        print(f"     PUT ingest: p50 {statistics.median(ms):.2f} ms, "
              f"p99 {ms[int(0.99 * len(ms))]:.2f} ms")
        before = put.status()["content"]
        ok3, refused3, times3 = stream(put, 30, 90.0, encoding="png")
        time.sleep(0.3)
        after = put.status()["content"]
        check(len(ok3) == 30 and not refused3,
              f"30 frames as PNG files through PUT: {len(ok3)} accepted, {refused3[:1]}")
        accounted(before, after, len(ok3), "PUT png")
        ms = sorted(t * 1e3 for t in times3)
        print(f"     PUT png ingest: p50 {statistics.median(ms):.2f} ms")
        lat = put.status()["scheduler"]["latency_us"]
        for stage in ("content received", "content to presented"):
            st = lat.get(stage)
            check(st is not None and st["count"] > 0, f"the daemon times {stage!r}")
            if st:
                print(f"     {stage}: n {st['count']}, p50 {st['p50_us']} us, "
                      f"p99 {st['p99_us']} us, max {st['max_us']} us")

        # Refusals: each counted under its reason, the frame on show unchanged. (The ring
        # client goes on after the PUT client's numbers, as a new client would.)
        d.seq = put.seq
        on_show = after["on_show_seq"]
        color, depth = frame(put, 1)
        bad = [
            ("wrong_size", lambda: d.send_rgbd(color[:-1], depth[:-1])),
            ("depth", lambda: d.send_rgbd(color, np.where(depth > 0, np.nan, depth))),
            ("invalid", lambda: d.send_rgbd(color, depth * 0 + 0.5, depth_units="vulkan")),
            ("depth", lambda: put.send_rgbd(color, -depth)),
        ]
        for kind, send in bad:
            before_n = d.status()["content"]["refused"].get(kind, 0)
            try:
                send()
                check(False, f"a {kind} frame is refused")
            except FrameRefused as e:
                n = d.status()["content"]["refused"].get(kind, 0)
                check(n == before_n + 1, f"a {kind} frame is refused and counted: {e.message}")
        # A stale sequence number: a client that starts over from 0.
        d.seq = 0
        try:
            d.send_rgbd(color, depth)
            check(False, "a stale sequence number is refused")
        except FrameRefused as e:
            check(e.status == 409, f"a stale sequence number is refused (409): {e.message}")
        time.sleep(0.2)
        check(d.status()["content"]["on_show_seq"] == on_show,
              "refused frames leave the frame on show")

        # A client killed mid-stream.
        killed = subprocess.Popen([sys.executable, "-c", f"""
import numpy as np, time
from dioptra_client import Dioptra
d = Dioptra({url!r})
c = np.full((d.height, d.width, 3), 7, np.uint8)
z = np.full((d.height, d.width), 1.0, np.float32)
while True:
    print(d.send_rgbd(c, z), flush=True)
    time.sleep(0.01)
"""], stdout=subprocess.PIPE, text=True)
        last = None
        for _ in range(20):
            last = int(killed.stdout.readline())
        killed.send_signal(signal.SIGKILL)
        killed.wait()
        time.sleep(0.5)
        s = put.status()
        check(s["content"]["on_show_seq"] >= last,
              f"after SIGKILL of a client the daemon shows its last frame "
              f"(#{s['content']['on_show_seq']}, the client's 20th answer was #{last})")
        shown = s["counts"]["frames_shown"]
        time.sleep(0.5)
        check(put.status()["counts"]["frames_shown"] > shown, "the display goes on")
        d.close()
        put.close()
    finally:
        code = rig.stop()
    check(code == 0, f"serve exited {code} on SIGTERM")
    if failures:
        print("".join(rig.log[-20:]), file=sys.stderr)
        sys.exit(f"{len(failures)} check(s) failed")
    print("all stream checks passed")


if __name__ == "__main__":
    main()

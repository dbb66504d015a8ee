#!/usr/bin/env python3
"""Checks dioptra's Lab Streaming Layer outlets with an independent consumer (pylsl).

Starts `dioptra serve` on the example simulated rig with `[lsl] enabled = true`, resolves
its three streams by name and type, reads them for a few seconds while it sets a manual
focus and starts and stops a recording through the API, and checks:
- each stream's type, channel count, format and channel labels (against `dioptra lsl --list
  --json`, and the gaze stream's labels, eyes and units in its XML description);
- gaze sample count against the tracker's rate, timestamps increasing and close to LSL's
  clock now (the outlet maps them from the host timeline);
- the lens stream carries the manual focus as a command; the marker stream carries frames,
  the control, the recording start and stop, and a lab's POST /marker;
- SIGTERM ends the daemon with exit 0.

    pip install pylsl
    cargo build --features lsl
    python3 scripts/check_lsl.py target/debug/dioptra

Exit code 0 when every check holds.
"""

import json
import os
import pathlib
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request

import pylsl

ROOT = pathlib.Path(__file__).resolve().parent.parent
SECONDS = 4.0
failures = []


def check(ok, what):
    print(("ok   " if ok else "FAIL ") + what)
    if not ok:
        failures.append(what)


def config(tmp: pathlib.Path, name: str) -> pathlib.Path:
    text = (ROOT / "crates/cli/examples/rig-sim.toml").read_text()
    text = text.replace("127.0.0.1:7420", "127.0.0.1:0")
    text = text.replace('dir = "recordings"', f'dir = "{tmp / "rec"}"')
    text += f'\n[lsl]\nenabled = true\nname = "{name}"\n'
    path = tmp / "rig.toml"
    path.write_text(text)
    return path


def call(addr: str, path: str, body=None):
    req = urllib.request.Request(
        f"http://{addr}{path}", method="POST" if body is not None else "GET",
        data=None if body is None else json.dumps(body).encode(),
        headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=10) as r:
        return json.load(r)


def channel_labels(info):
    labels, units = [], []
    ch = info.desc().child("channels").child("channel")
    while not ch.empty():
        labels.append(ch.child_value("label"))
        units.append((ch.child_value("eye"), ch.child_value("type"), ch.child_value("unit")))
        ch = ch.next_sibling()
    return labels, units


def drain(inlet, into, stamps):
    samples, ts = inlet.pull_chunk(timeout=0.0, max_samples=100000)
    into.extend(samples)
    stamps.extend(ts)


def main():
    binary = sys.argv[1] if len(sys.argv) > 1 else str(ROOT / "target/debug/dioptra")
    name = f"dioptra-check-{os.getpid()}"
    tmp = pathlib.Path(tempfile.mkdtemp())
    cfg = config(tmp, name)
    listing = json.loads(subprocess.run(
        [binary, "lsl", "--list", "--json", "--config", str(cfg)],
        check=True, capture_output=True, text=True).stdout)
    check(listing["built_with_lsl"], "the binary was built with LSL")
    specs = {s["type"]: s for s in listing["streams"]}

    p = subprocess.Popen([binary, "serve", "--config", str(cfg)],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    addr = None
    for line in p.stderr:
        m = re.search(r"API on http://(\S+)", line)
        if m:
            addr = m.group(1)
            break
    if addr is None:
        sys.exit(f"serve ended before it listened (exit {p.wait()})")
    log = []
    threading.Thread(target=lambda: log.extend(p.stderr), daemon=True).start()

    try:
        inlets = {}
        for kind in ("Gaze", "Lens", "Markers"):
            spec = specs[kind]
            found = pylsl.resolve_byprop("name", spec["name"], minimum=1, timeout=20.0)
            check(len(found) == 1, f"{spec['name']} resolved by name")
            if not found:
                continue
            info = found[0]
            check(info.type() == kind, f"{spec['name']} has type {kind} ({info.type()})")
            check(info.channel_count() == len(spec["channels"]),
                  f"{spec['name']}: {info.channel_count()} channels, "
                  f"{len(spec['channels'])} declared")
            by_type = pylsl.resolve_bypred(f"type='{kind}' and name='{spec['name']}'",
                                           minimum=1, timeout=10.0)
            check(len(by_type) == 1, f"{spec['name']} resolved by type")
            inlet = pylsl.StreamInlet(info, max_buflen=60)
            full = inlet.info(timeout=10.0)
            labels, units = channel_labels(full)
            check(labels == [c["label"] for c in spec["channels"]],
                  f"{spec['name']}: the XML description's channel labels")
            if kind == "Gaze":
                want = [(c.get("eye", ""), c["type"], c["unit"]) for c in spec["channels"]]
                check(units == want, "gaze channels carry eye, type and unit")
            inlet.open_stream(timeout=10.0)
            inlets[kind] = inlet
        if len(inlets) < 3:
            raise SystemExit(1)

        data = {k: ([], []) for k in inlets}
        t_end = time.time() + SECONDS
        acted = False
        while time.time() < t_end:
            time.sleep(0.1)
            for k, inlet in inlets.items():
                drain(inlet, *data[k])
            if not acted and time.time() > t_end - SECONDS / 2:
                call(addr, "/focus", {"diopters": 2.0})
                call(addr, "/recording/start", {"name": "lslcheck"})
                marked = call(addr, "/marker", {"marker": {"trial": 3, "stimulus": "on"}})
                time.sleep(0.3)
                call(addr, "/recording/stop", {})
                acted = True
        time.sleep(0.5)
        now = pylsl.local_clock()
        for k, inlet in inlets.items():
            drain(inlet, *data[k])

        gaze, gts = data["Gaze"]
        rate = specs["Gaze"]["rate_hz"]
        check(len(gaze) >= 0.5 * rate * SECONDS,
              f"{len(gaze)} gaze samples in {SECONDS} s at {rate} Hz")
        check(all(len(s) == len(specs["Gaze"]["channels"]) for s in gaze),
              "every gaze sample has every channel")
        check(all(b >= a for a, b in zip(gts, gts[1:])), "gaze timestamps never go back")
        check(bool(gts) and 0 <= now - gts[-1] < 2.0,
              f"the newest gaze timestamp is {now - gts[-1]:.3f} s before LSL's clock now"
              if gts else "gaze timestamps exist")
        labels = [c["label"] for c in specs["Gaze"]["channels"]]
        host = labels.index("host_time")
        spans = (gts[-1] - gts[0], gaze[-1][host] - gaze[0][host]) if gaze else (0, 1)
        check(abs(spans[0] - spans[1]) < 1e-3,
              "LSL timestamps advance with the host_time channel")

        lens, lts = data["Lens"]
        check(any(s[0] == 1.0 and abs(s[1] - 2.0) < 1e-6 for s in lens),
              "the lens stream has the 2 D command")
        check(any(s[0] == 2.0 and s[2] == s[2] for s in lens),
              "the lens stream has read-backs with a power")
        check(all(b >= a - 0.05 for a, b in zip(lts, lts[1:])),
              "lens timestamps in order (commands on the wire, replies after)")

        marks = [json.loads(s[0]) for s in data["Markers"][0]]
        events = {m["event"] for m in marks}
        check("frame" in events, "markers have frames")
        check(any(m["event"] == "control" and m.get("kind") == "manual_focus"
                  and m.get("diopters") == 2.0 for m in marks),
              "markers have the manual focus control")
        check(any(m["event"] == "recording_start" and m.get("name") == "lslcheck"
                  for m in marks), "markers have the recording start with its name")
        check("recording_stop" in events, "markers have the recording stop")
        lab = [(m, t) for m, t in zip(marks, data["Markers"][1]) if m["event"] == "marker"]
        check(len(lab) == 1 and lab[0][0]["marker"] == {"trial": 3, "stimulus": "on"},
              f"markers have the POST /marker one: {lab}")
        if lab and gaze:
            # Its LSL time is the host time POST /marker answered, on the gaze stream's
            # mapping from the host timeline (its host_time channel) to LSL's clock.
            offset = gts[-1] - gaze[-1][host]
            stamp = marked["host_ns"] / 1e9 + offset
            check(abs(lab[0][1] - stamp) < 1e-3,
                  f"the marker's LSL time is its host time ({lab[0][1] - stamp:+.6f} s)")
        status = call(addr, "/status")
        check(status["lsl"]["dropped"] == 0, f"/status lsl: {status['lsl']}")
    finally:
        p.send_signal(signal.SIGTERM)
        try:
            code = p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()
            code = "killed after 30 s"
    check(code == 0, f"serve exited {code} on SIGTERM")
    if failures:
        print("".join(log[-20:]), file=sys.stderr)
        sys.exit(f"{len(failures)} check(s) failed")
    print("all LSL checks passed")


if __name__ == "__main__":
    main()

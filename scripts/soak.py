#!/usr/bin/env python3
"""Soak test of `dioptra serve` on the simulated rig, with independent clients.

The example rig with its tracker at 1 kHz runs for --seconds while this script polls
GET /status at 10 Hz and reads the /stream WebSocket (websocket-client), recording all the
while. At the end it reports RSS at start and end, gaze samples against the tracker's rate,
stream messages lost to lag, recording drops and render errors. Then a second daemon records
for --kill-after seconds and is killed with SIGKILL; the official `mcap` reader reads the cut
file, and `dioptra recording recover` rewrites it.

    pip install websocket-client mcap
    cargo build --release
    python3 scripts/soak.py --seconds 600

Exit code 0 when nothing was dropped and no render failed.
"""

import argparse
import json
import pathlib
import subprocess
import sys
import tempfile
import threading
import time

import websocket  # websocket-client
from mcap.reader import NonSeekingReader, make_reader

from dioptra_client.daemon import Daemon, rig_config

ROOT = pathlib.Path(__file__).resolve().parent.parent


def start(binary: str, tmp: pathlib.Path, record: bool) -> Daemon:
    """The example rig with its tracker at 1 kHz, recording from the start if `record`."""
    cfg = rig_config(tmp / "rig.toml", (ROOT / "crates/cli/examples/rig-sim.toml").read_text(),
                     replace={"sim_rate_hz = 250.0": "sim_rate_hz = 1000.0",
                              "start = false": f"start = {'true' if record else 'false'}"})
    return Daemon(binary, cfg).start()


def rss_kib(pid: int) -> int:
    for line in pathlib.Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return -1


def wait_ok(d):
    for _ in range(600):
        s = d.status()
        if all(s["devices"][d]["state"] == "ok" for d in ("lens", "gaze", "sync")):
            return s
        time.sleep(0.1)
    sys.exit("the devices never came up")


def soak(binary: str, seconds: float) -> bool:
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="dioptra-soak-"))
    rig = start(binary, tmp, record=True)
    d = rig.client()
    stream = {"messages": 0, "gaze": 0, "lagged_skipped": 0, "errors": 0}
    stop = threading.Event()

    def reader():
        ws = websocket.create_connection(rig.url.replace("http://", "ws://") + "/stream",
                                         timeout=10)
        while not stop.is_set():
            try:
                m = json.loads(ws.recv())
            except Exception:
                stream["errors"] += 1
                break
            stream["messages"] += 1
            if m.get("type") == "gaze":
                stream["gaze"] += 1
            elif m.get("type") == "lagged":
                stream["lagged_skipped"] += m["skipped"]
        ws.close()

    wait_ok(d)
    time.sleep(5)  # past start-up allocations
    first = d.status()
    rss0 = rss_kib(rig.pid)
    t = threading.Thread(target=reader, daemon=True)
    t.start()
    polls, t_end = 0, time.monotonic() + seconds
    while time.monotonic() < t_end:
        d.status()
        polls += 1
        time.sleep(0.1)
    last = d.status()
    rss1 = rss_kib(rig.pid)
    stop.set()
    rec = d.stop_recording()
    d.shutdown()
    code = rig.wait(timeout=60)
    span = last["uptime_s"] - first["uptime_s"]
    samples = last["counts"]["gaze_samples"] - first["counts"]["gaze_samples"]
    print(f"soak: {span:.0f} s, {polls} status polls, exit {code}")
    print(f"  RSS {rss0} KiB at start, {rss1} KiB at end ({rss1 - rss0:+d} KiB)")
    print(f"  gaze samples {samples} ({samples / span:.1f} Hz; the tracker sends 1000 Hz)")
    print(f"  stream: {stream['messages']} messages, {stream['gaze']} gaze, "
          f"{stream['lagged_skipped']} skipped by lag, {stream['errors']} errors")
    print(f"  recording: {rec['messages']} messages, {rec['dropped']} dropped")
    print(f"  render errors {last['counts']['render_errors']}, "
          f"frames shown {last['counts']['frames_shown']}")
    ok = (rec["dropped"] == 0 and stream["lagged_skipped"] == 0
          and last["counts"]["render_errors"] == 0 and code == 0
          and abs(samples / span - 1000.0) < 10.0)
    return ok


def killed(binary: str, after: float) -> bool:
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="dioptra-kill-"))
    rig = start(binary, tmp, record=True)
    d = rig.client()
    wait_ok(d)
    time.sleep(after)
    sent = d.status()["recording"]
    rig.kill()
    files = list((tmp / "rec").glob("*.mcap"))
    f = files[0]

    def count(reader):
        n, error = 0, None
        with open(f, "rb") as fh:
            try:
                for _ in reader(fh).iter_messages(log_time_order=False):
                    n += 1
            except Exception as e:  # the cut chunk
                error = f"{type(e).__name__}: {str(e)[:80]}"
        return n, error

    print(f"SIGKILL after {after:.0f} s: {f.stat().st_size} bytes")
    for name, reader in (("make_reader", make_reader), ("NonSeekingReader", NonSeekingReader)):
        n, error = count(reader)
        print(f"  the official reader ({name}, log_time_order=False) read {n} messages"
              + (f", then {error}" if error else " and no error"))
    print(f"  status just before the kill: {json.dumps(sent)}")
    out = tmp / "fixed.mcap"
    r = subprocess.run([binary, "recording", "recover", str(f), "--out", str(out)],
                       capture_output=True, text=True)
    print("  " + r.stdout.strip())
    m = 0
    with open(out, "rb") as fh:
        for _ in make_reader(fh).iter_messages():
            m += 1
    print(f"  the official reader reads {m} messages from the recovered file")
    return r.returncode == 0 and m > 0


def main():
    a = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    a.add_argument("--binary", default=str(ROOT / "target/release/dioptra"))
    a.add_argument("--seconds", type=float, default=600.0)
    a.add_argument("--kill-after", type=float, default=10.0)
    args = a.parse_args()
    ok = killed(args.binary, args.kill_after)
    ok = soak(args.binary, args.seconds) and ok
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()

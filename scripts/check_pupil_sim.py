#!/usr/bin/env python3
"""Checks `dioptra sim pupil-capture` with Pupil Labs' own client, an independent peer.

Starts the simulator on a free port, connects with pupil-core-network-client (pyzmq/libzmq),
estimates the clock offset as that client does, subscribes to "gaze.3d." and checks that the
messages carry the topics and payload fields Pupil Capture sends, with monotonic timestamps
near the client's estimate of Pupil time. Pupil Remote's other commands are checked over a
plain pyzmq REQ socket. Exits 0 when everything holds, 1 otherwise (with what failed).

    pip install pupil-core-network-client msgpack pyzmq
    python3 scripts/check_pupil_sim.py [--binary target/debug/dioptra] [--messages 300]
"""

import argparse
import math
import os
import signal
import subprocess
import sys
import time

import msgpack
import zmq
from pupil_labs.pupil_core_network_client import Device

BINOCULAR = ("topic", "norm_pos", "gaze_point_3d", "eye_centers_3d", "gaze_normals_3d",
             "confidence", "timestamp", "base_data")
MONOCULAR = ("topic", "norm_pos", "gaze_point_3d", "eye_center_3d", "gaze_normal_3d",
             "confidence", "timestamp", "base_data")
PUPIL = ("topic", "id", "method", "timestamp", "confidence", "norm_pos", "diameter",
         "diameter_3d", "ellipse", "sphere", "circle_3d", "theta", "phi")

failures = []


def check(ok, what):
    if not ok:
        failures.append(what)
        print("FAIL:", what, file=sys.stderr)
    return ok


def vec(v, n):
    return isinstance(v, (list, tuple)) and len(v) == n and all(
        isinstance(x, (int, float)) and math.isfinite(x) for x in v)


def check_payload(topic, p, i):
    where = f"message {i} ({topic})"
    if topic.startswith("gaze.3d.01."):
        fields = BINOCULAR
    elif topic.startswith(("gaze.3d.0.", "gaze.3d.1.")):
        fields = MONOCULAR
    else:
        return check(False, f"{where}: topic is not a gaze.3d.* topic")
    missing = [f for f in fields if f not in p]
    if not check(not missing, f"{where}: missing {missing}"):
        return False
    check(p["topic"] == topic, f"{where}: payload topic {p['topic']!r}")
    check(vec(p["norm_pos"], 2), f"{where}: norm_pos {p['norm_pos']!r}")
    check(vec(p["gaze_point_3d"], 3), f"{where}: gaze_point_3d")
    check(isinstance(p["confidence"], float) and 0.0 <= p["confidence"] <= 1.0,
          f"{where}: confidence {p['confidence']!r}")
    check(isinstance(p["timestamp"], float), f"{where}: timestamp {p['timestamp']!r}")
    if fields is BINOCULAR:
        for key in ("eye_centers_3d", "gaze_normals_3d"):
            d = p[key]
            check(isinstance(d, dict) and sorted(d) == ["0", "1"]
                  and all(vec(v, 3) for v in d.values()), f"{where}: {key} {d!r}")
        ids = sorted(b.get("id") for b in p["base_data"] if isinstance(b, dict))
        check(ids == [0, 1], f"{where}: base_data ids {ids}")
    else:
        check(vec(p["eye_center_3d"], 3) and vec(p["gaze_normal_3d"], 3), f"{where}: eye vectors")
        eye = int(topic.split(".")[2])
        ids = [b.get("id") for b in p["base_data"] if isinstance(b, dict)]
        check(ids == [eye], f"{where}: base_data ids {ids}")
    for b in p["base_data"]:
        missing = [f for f in PUPIL if f not in b]
        check(not missing, f"{where}: base_data datum missing {missing}")
        check(b.get("topic") == f"pupil.{b.get('id')}.3d", f"{where}: pupil topic {b.get('topic')!r}")
        d = b.get("diameter_3d")
        check(isinstance(d, float) and 1.0 < d < 10.0, f"{where}: diameter_3d {d!r} mm")
    if fields is BINOCULAR:
        # Eye 0 is the right eye: in the world camera's frame (x right) it sits right of eye 1.
        check(p["eye_centers_3d"]["0"][0] > p["eye_centers_3d"]["1"][0],
              f"{where}: eye 0 (the right eye) is not right of eye 1")
    return True


def remote_commands(port):
    """Pupil Remote's replies to the commands Capture documents, over a bare REQ socket."""
    ctx = zmq.Context.instance()
    req = ctx.socket(zmq.REQ)
    req.setsockopt(zmq.RCVTIMEO, 3000)
    req.setsockopt(zmq.LINGER, 0)
    req.connect(f"tcp://127.0.0.1:{port}")

    def ask(*frames):
        if len(frames) == 1:
            req.send_string(frames[0])
        else:
            req.send_multipart(frames)
        return req.recv_string()

    sub_port = ask("SUB_PORT")
    check(sub_port.isdigit(), f"SUB_PORT answered {sub_port!r}")
    pub_port = ask("PUB_PORT")
    check(pub_port.isdigit() and pub_port != sub_port, f"PUB_PORT answered {pub_port!r}")
    t0 = float(ask("t"))
    check(ask("T 100.0") == "Timesync successful.", "T 100.0 was not accepted")
    t1 = float(ask("t"))
    check(100.0 <= t1 < 110.0, f"after T 100.0, t answered {t1} (before: {t0})")
    check(ask("T abc") == "'abc' cannot be converted to float.", "T abc was not refused")
    check(ask("T " + repr(t0 + 1.0)) == "Timesync successful.", "resetting the time base")
    check(ask("v") != "", "v answered nothing")
    check(ask("R") == "OK" and ask("r") == "OK", "R / r")
    check(ask("C") == "OK" and ask("c") == "OK", "C / c")
    check(ask("nonsense") == "Unknown command.", "an unknown command was not refused")
    note = msgpack.packb({"subject": "check", "topic": "notify.check"}, use_bin_type=True)
    check(ask(b"notify.check", note) == "Message forwarded.", "a notification was not forwarded")
    # A peer on PUB_PORT (what the client's high-frequency sending uses) is accepted.
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    pub.connect(f"tcp://127.0.0.1:{pub_port}")
    pub.send_multipart([b"notify.check", note])
    pub.close()
    req.close()
    print(f"pupil remote: SUB_PORT {sub_port}, PUB_PORT {pub_port}, t {t0:.3f}, T/t/v/R/r/C/c/notify ok")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--binary", default=os.path.join("target", "debug", "dioptra"))
    ap.add_argument("--messages", type=int, default=300)
    args = ap.parse_args()

    proc = subprocess.Popen([args.binary, "sim", "pupil-capture", "--port", "0"],
                            stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline().split()
        # "pupil remote 127.0.0.1:PORT sub_port N pub_port M"
        if len(line) < 3 or line[:2] != ["pupil", "remote"]:
            print(f"unexpected first line from the simulator: {line!r}", file=sys.stderr)
            return 1
        port = int(line[2].rsplit(":", 1)[1])
        print(f"simulator: Pupil Remote on 127.0.0.1:{port}")

        remote_commands(port)

        device = Device(address="127.0.0.1", port=port)
        stats = device.estimate_client_to_remote_clock_offset(num_measurements=20)
        check(math.isfinite(stats.mean_offset) and stats.std_offset < 0.05,
              f"clock offset {stats}")
        print(f"clock offset: mean {stats.mean_offset:.6f} s, std {stats.std_offset * 1e6:.1f} us "
              f"({stats.num_measurements} measurements); version {device.request_version()!r}")

        topics = {}
        last_ts = -math.inf
        sub = device.subscribe("gaze.3d.")
        with sub:
            deadline = time.monotonic() + 60
            got = 0
            while got < args.messages and time.monotonic() < deadline:
                msg = sub.recv_new_message(timeout_ms=2000)
                if msg is None:
                    check(False, "no gaze message within 2 s")
                    break
                got += 1
                topics[msg.topic] = topics.get(msg.topic, 0) + 1
                check_payload(msg.topic, msg.payload, got)
                ts = msg.payload.get("timestamp", math.nan)
                check(ts > last_ts, f"message {got}: timestamp {ts} after {last_ts}")
                last_ts = ts
                # The datum's Pupil time is close to the client's estimate of Pupil time now.
                lag = device.current_pupil_time() - ts
                check(-0.05 < lag < 1.0, f"message {got}: {lag:.3f} s between now and its timestamp")
        check(got >= args.messages, f"only {got} of {args.messages} gaze messages")
        check(topics.get("gaze.3d.01.", 0) > 0, f"no binocular datum among {topics}")
        print(f"received {got} gaze messages: {topics}; last timestamp {last_ts:.3f}")
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            rc = proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            rc = None
    check(rc == 0, f"the simulator exited with {rc} on SIGTERM")
    if failures:
        print(f"{len(failures)} checks failed", file=sys.stderr)
        return 1
    print("pupil-capture simulator: all checks passed")
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Checks dioptra's Pupil driver (zmq.rs) against libzmq peers: a stand-in for Pupil Capture
made of pyzmq sockets and Python's msgpack, as Capture itself is.

Pupil Remote (REP) answers SUB_PORT, PUB_PORT, t, v and notifications; the publisher sends
binocular gaze.3d.01. datums at 200 Hz, stamped with the same clock that `t` answers, looking
up (Pupil's y axis points down), every 10th one below the confidence threshold. Then
`dioptra gaze --device pupil:127.0.0.1:PORT stream --count N` must print N samples with
both eyes valid and looking up (positive pitch in dioptra's y-up frame), the low-confidence
ones as dropouts, device times increasing, and host times (Pupil time moved by the measured
offset) just before receipt. Exits 0 when all holds, 1 otherwise.

    pip install msgpack pyzmq
    python3 scripts/check_pupil_driver.py [--binary target/debug/dioptra] [--count 200]
"""

import argparse
import os
import subprocess
import sys
import threading
import time

import msgpack
import zmq

OFFSET_S = 5000.0  # Pupil time = this process's monotonic clock + OFFSET_S


def pupil_time():
    return time.monotonic() + OFFSET_S


def serve(stop, ctx):
    rep = ctx.socket(zmq.REP)
    pub = ctx.socket(zmq.PUB)
    sub = ctx.socket(zmq.SUB)
    for s in (rep, pub, sub):
        s.setsockopt(zmq.LINGER, 0)
    remote_port = rep.bind_to_random_port("tcp://127.0.0.1")
    sub_port = pub.bind_to_random_port("tcp://127.0.0.1")
    pub_port = sub.bind_to_random_port("tcp://127.0.0.1")

    def remote():
        poller = zmq.Poller()
        poller.register(rep, zmq.POLLIN)
        while not stop.is_set():
            if not poller.poll(100):
                continue
            frames = rep.recv_multipart()
            cmd = frames[0].decode()
            if len(frames) > 1:
                reply = "Message forwarded."
            elif cmd == "SUB_PORT":
                reply = str(sub_port)
            elif cmd == "PUB_PORT":
                reply = str(pub_port)
            elif cmd == "t":
                reply = repr(pupil_time())
            elif cmd == "v":
                reply = "3.5.1-libzmq-stand-in"
            else:
                reply = "Unknown command."
            rep.send_string(reply)

    def publish():
        i = 0
        while not stop.is_set():
            i += 1
            conf = 0.3 if i % 10 == 0 else 0.9
            datum = {
                "topic": "gaze.3d.01.",
                # Eye 0 is the right eye (+x); y down, so these normals look up.
                "eye_centers_3d": {"0": [31.0, 0.0, -20.0], "1": [-33.0, 0.0, -20.0]},
                "gaze_normals_3d": {"0": [-0.05, -0.3, 0.95], "1": [0.05, -0.3, 0.95]},
                "gaze_point_3d": [0.0, -160.0, 500.0],
                "norm_pos": [0.5, 0.8],
                "confidence": conf,
                "timestamp": pupil_time(),
                "base_data": [
                    {"topic": "pupil.0.3d", "id": 0, "confidence": conf, "diameter_3d": 3.5},
                    {"topic": "pupil.1.3d", "id": 1, "confidence": conf, "diameter_3d": 3.4},
                ],
            }
            pub.send_multipart([b"gaze.3d.01.", msgpack.packb(datum, use_bin_type=True)])
            time.sleep(0.005)

    threads = [threading.Thread(target=remote), threading.Thread(target=publish)]
    for t in threads:
        t.start()
    return remote_port, threads, (rep, pub, sub)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--binary", default=os.path.join("target", "debug", "dioptra"))
    ap.add_argument("--count", type=int, default=200)
    args = ap.parse_args()
    ctx = zmq.Context.instance()
    stop = threading.Event()
    port, threads, sockets = serve(stop, ctx)
    failures = []
    try:
        out = subprocess.run(
            [args.binary, "gaze", "--device", f"pupil:127.0.0.1:{port}", "stream",
             "--count", str(args.count)],
            capture_output=True, text=True, timeout=120)
    finally:
        stop.set()
        for t in threads:
            t.join()
        for s in sockets:
            s.close()
    if out.returncode != 0:
        print(out.stdout, out.stderr, file=sys.stderr)
        print(f"dioptra exited with {out.returncode}", file=sys.stderr)
        return 1
    rows = [l.split() for l in out.stdout.splitlines()]
    rows = [r for r in rows if r and r[0][0].isdigit()]
    if len(rows) != args.count:
        failures.append(f"{len(rows)} samples printed, expected {args.count}")
    valid = dropouts = 0
    last_device = -1
    for r in rows:
        host, device_us, receive = float(r[0]), int(r[1]), float(r[2])
        l_ok, r_ok = r[3], r[6]
        if device_us <= last_device:
            failures.append(f"device time {device_us} after {last_device}")
        last_device = device_us
        # Pupil time (~5000 s + this clock) moved by the offset lands just before receipt.
        if not (-0.005 <= receive - host < 0.5):
            failures.append(f"host time {host} against receipt {receive}")
        if l_ok == "1" and r_ok == "1":
            valid += 1
            l_pitch, r_pitch = float(r[5]), float(r[8])
            if not (l_pitch > 10.0 and r_pitch > 10.0):
                failures.append(f"looking up came out as pitch {l_pitch}, {r_pitch}")
        elif l_ok == "0" and r_ok == "0":
            dropouts += 1
        else:
            failures.append(f"one eye valid in a binocular datum: {r}")
    if not (valid > 0 and dropouts > 0):
        failures.append(f"{valid} valid samples and {dropouts} dropouts")
    info = out.stderr.strip().splitlines()[-1:] if out.stderr.strip() else []
    for f in failures[:20]:
        print("FAIL:", f, file=sys.stderr)
    if failures:
        return 1
    print(f"pupil driver against libzmq peers: {len(rows)} samples, {valid} valid, "
          f"{dropouts} low-confidence dropouts, device times increasing, host times just before "
          f"receipt {info}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

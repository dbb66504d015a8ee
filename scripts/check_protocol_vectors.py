#!/usr/bin/env python3
"""Checks firmware-protocol/vectors/vectors.txt against PROTOCOL.md with code that shares
nothing with the Rust crate (which uses the crc and cobs crates and postcard): the bitwise
CRC-32/ISCSI of PROTOCOL.md 1.2, COBS as section 1.1 describes it, and the photodiode messages'
fields decoded by hand (section 2's varints). Exit status 1 on any mismatch."""
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
VERSION = 2


def crc32c(data):
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def cobs_decode(wire):
    out, i = [], 0
    while i < len(wire):
        code = wire[i]
        if code == 0 or i + code > len(wire):
            raise ValueError("bad COBS code")
        out += wire[i + 1:i + code]
        i += code
        if code != 0xFF and i < len(wire):
            out.append(0)
    return out


def varint(data, i):
    value, shift = 0, 0
    while True:
        b = data[i]
        value |= (b & 0x7F) << shift
        i += 1
        if not b & 0x80:
            return value, i
        shift += 7


def main():
    failures = 0
    lines = (ROOT / "firmware-protocol/vectors/vectors.txt").read_text().splitlines()
    seen = []
    for line in lines:
        if line.startswith("#") or not line.strip():
            continue
        name, request_id, hexbytes = line.split()
        wire = list(bytes.fromhex(hexbytes))
        try:
            assert wire[-1] == 0 and 0 not in wire[:-1], "one 0x00, at the end"
            body = cobs_decode(wire[:-1])
            assert body[0] == VERSION, f"version byte {body[0]}"
            assert int.from_bytes(bytes(body[1:3]), "little") == int(request_id), "request id"
            crc = int.from_bytes(bytes(body[-4:]), "little")
            assert crc == crc32c(body[:-4]), f"CRC {crc:#010x} != {crc32c(body[:-4]):#010x}"
            message = body[3:-4]
            if name == "PhotodiodeConfig":
                assert message[0] == 17
                assert message[1] == 1, "enabled"
                threshold, i = varint(message, 2)
                hysteresis, i = varint(message, i)
                assert (threshold, hysteresis, i) == (32768, 2000, len(message))
            if name == "PhotodiodeEdge":
                assert message[0] == 18
                edge, i = varint(message, 1)
                t, i = varint(message, i)
                rising = message[i]
                level, i = varint(message, i + 1)
                assert (edge, t, rising, level, i) == (300, 124011111, 1, 51234, len(message))
            seen.append(name)
        except (AssertionError, ValueError, IndexError) as e:
            failures += 1
            print(f"FAIL {name}: {e}")
    print(f"{len(seen)} vectors checked: {', '.join(seen)}")
    if "PhotodiodeEdge" not in seen or "PhotodiodeConfig" not in seen:
        print("FAIL: the photodiode vectors are missing")
        failures += 1
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())

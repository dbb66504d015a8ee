"""The shared-memory ring's slot layout against the golden bytes that the daemon's Rust tests
check too (crates/rig/ring-golden.json, specified in crates/rig/RING.md), and against the
layout a running daemon announces."""

import json
import math
import struct

from conftest import GOLDEN
from dioptra_client import frames


def golden():
    return json.loads(GOLDEN.read_text())


def test_the_client_packs_the_golden_slot_header():
    g = golden()["slot_header"]
    v = g["values"]
    num = {"inf": math.inf, "nan": math.nan}
    head = frames.pack_slot_header(
        v["seq"], frames.COLOR_CODES[v["color_format"]], frames.DEPTH_CODES[v["depth_kind"]],
        num.get(v["near"], v["near"]), num.get(v["far"], v["far"]), v["width"], v["height"],
        v["app_time_ns"], v["color_bytes"], v["depth_bytes"])
    assert head.hex() == g["hex"]
    assert frames.slot_layout() == {k: list(x) for k, x in g["layout"].items()}


def test_codes_and_ring_header_match_the_spec():
    g = golden()
    assert frames.COLOR_CODES == g["color_formats"]
    assert frames.DEPTH_CODES == g["depth_kinds"]
    ring = bytes.fromhex(g["ring_header"]["hex"])
    assert ring[:8] == frames.RING_MAGIC
    version, slots = struct.unpack_from("<II", ring, 8)
    assert (version, slots) == (frames.RING_VERSION, g["slots"])


def test_the_daemon_announces_the_same_layout(stream_rig):
    with stream_rig.client() as d:
        info = d._http.request("GET", "/frame/ring")
        g = golden()
        assert info["slot_header"] == g["slot_header"]["layout"]
        assert info["version"] == frames.RING_VERSION and info["slots"] == g["slots"]
        assert info["slot_bytes"] == 64 + info["width"] * info["height"] * 16
        assert d.uses_ring


def test_the_client_packs_the_golden_eye_field():
    """The right eye's half of a pair: ``eye`` 2 at offset 56, as the daemon reads it."""
    g = golden()
    v = g["slot_header_right_eye"]["values"]
    num = {"inf": math.inf, "nan": math.nan}
    head = frames.pack_slot_header(
        v["seq"], frames.COLOR_CODES[v["color_format"]], frames.DEPTH_CODES[v["depth_kind"]],
        num.get(v["near"], v["near"]), num.get(v["far"], v["far"]), v["width"], v["height"],
        v["app_time_ns"], v["color_bytes"], v["depth_bytes"], frames.EYE_CODES[v["eye"]])
    assert head.hex() == g["slot_header_right_eye"]["hex"]
    assert struct.unpack_from("<I", head, 56) == (2,)
    assert frames.EYE_CODES == g["eyes"]


def test_the_client_packs_the_golden_view_field():
    """View 6 of a 4 x 4 grid (row 1, column 1): ``view`` 6 at offset 60, as the daemon reads it."""
    g = golden()["slot_header_view"]
    v = g["values"]
    num = {"inf": math.inf, "nan": math.nan}
    head = frames.pack_slot_header(
        v["seq"], frames.COLOR_CODES[v["color_format"]], frames.DEPTH_CODES[v["depth_kind"]],
        num.get(v["near"], v["near"]), num.get(v["far"], v["far"]), v["width"], v["height"],
        v["app_time_ns"], v["color_bytes"], v["depth_bytes"], frames.EYE_CODES[v["eye"]],
        v["view"])
    assert head.hex() == g["hex"]
    assert struct.unpack_from("<I", head, 60) == (6,)

"""Stream RGB-D frames from an application to a running dioptra daemon.

The daemon must run with ``[content] source = "stream"``. On the same machine frames go
through the daemon's shared-memory ring (``GET /frame/ring``): the client writes a frame into
a slot and names it with ``POST /frame``; the daemon copies it out before it answers. Where
the ring cannot be opened (another machine, no permission) frames go as the body of
``PUT /frame``. Either way ``send_rgbd`` returns the frame's sequence number, or raises
``FrameRefused`` with the daemon's reason (wrong size, NaN depth, ...). With
``encoding="png"`` a frame goes as ``PUT /frame`` with a PNG colour file and a 16-bit PNG depth
file (whole millimetres), a fraction of the raw bytes over a network.

    import numpy as np
    from dioptra_client import Dioptra

    d = Dioptra("http://127.0.0.1:7420")
    color = np.zeros((d.height, d.width, 3), np.uint8)       # sRGB
    depth = np.full((d.height, d.width), 0.5, np.float32)    # metres
    d.send_rgbd(color, depth, depth_units="m")
"""

from __future__ import annotations

import http.client
import json
import mmap
import os
import struct
import time
import urllib.parse
import zlib

import numpy as np

__all__ = ["Dioptra", "DioptraError", "FrameRefused", "DEPTH_UNITS"]

#: Depth conventions the daemon converts on ingest (a depth buffer needs ``near`` and ``far``).
DEPTH_UNITS = ("m", "mm", "D", "gl", "gl-reversed", "vulkan", "vulkan-reversed", "d3d",
               "d3d-reversed")
_DEPTH_CODES = {"m": 1, "D": 2, "gl": 3, "gl-reversed": 4, "vulkan": 5, "vulkan-reversed": 6,
                "d3d": 5, "d3d-reversed": 6, "mm": 7}
_COLOR_CODES = {"rgb8": 1, "rgba8": 2, "rgbf32": 3}
_MAGIC = b"DIOPTRA1"


class DioptraError(Exception):
    """The daemon answered with an error (``status`` is the HTTP status)."""

    def __init__(self, status: int, message: str):
        super().__init__(f"{status}: {message}")
        self.status = status
        self.message = message


class FrameRefused(DioptraError):
    """The daemon refused a frame; the frame on show stays."""


class Dioptra:
    """A connection to one daemon's API (``url``: ``http://host:port``)."""

    def __init__(self, url: str = "http://127.0.0.1:7420", token: str | None = None,
                 use_ring: bool = True, timeout: float = 10.0):
        u = urllib.parse.urlparse(url)
        if u.scheme != "http" or not u.hostname:
            raise ValueError(f"{url!r}: expected http://host:port")
        self._host, self._port = u.hostname, u.port or 80
        self._timeout = timeout
        self._headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._conn = None
        ring = self._request("GET", "/frame/ring")
        self._ring = None
        if use_ring and ring.get("path"):
            try:
                self._ring = _Ring(ring)
            except OSError:
                self._ring = None  # Not on this machine, or no permission: PUT /frame.
        status = self.status()
        content = status.get("content", {})
        if content.get("source") != "stream":
            raise DioptraError(409, "the daemon's content is not a stream: set [content] "
                                    "source = \"stream\" in its rig config")
        #: The display's size: every frame must be this size.
        self.width, self.height = int(ring["width"]), int(ring["height"])
        # Sequence numbers must grow across clients: continue after the newest accepted.
        self._seq = int(content.get("newest_seq") or 0)

    @property
    def uses_ring(self) -> bool:
        """Whether frames go through shared memory (else ``PUT /frame``)."""
        return self._ring is not None

    def status(self) -> dict:
        """The daemon's ``GET /status``."""
        return self._request("GET", "/status")

    def send_rgbd(self, color, depth, depth_units: str = "m", near: float | None = None,
                  far: float | None = None, app_time_ns: int | None = None,
                  encoding: str = "raw") -> int:
        """Sends one frame; returns its sequence number.

        ``color``: H x W x 3 or 4 ``uint8`` (sRGB), or H x W x 3 float (linear light).
        ``depth``: H x W, in ``depth_units`` (see ``DEPTH_UNITS``); a depth buffer
        (``gl``, ``vulkan``, ...) needs ``near`` and ``far`` in metres (``far=float("inf")``
        for an infinite reversed-Z projection). H x W must be the daemon's display size.
        ``encoding="png"`` (``uint8`` colour, depth in ``m`` or ``mm``) sends PNG files through
        ``PUT /frame``: depth in whole millimetres from 1 mm to 65.535 m (farther, infinity
        included, is sent as 65.535 m).
        """
        if encoding == "png":
            return self._send_png(color, depth, depth_units, app_time_ns)
        if encoding != "raw":
            raise ValueError(f"encoding {encoding!r}: expected 'raw' or 'png'")
        color = np.asarray(color)
        depth = np.asarray(depth)
        if color.ndim != 3 or color.shape[2] not in (3, 4):
            raise ValueError(f"color must be H x W x 3 or 4, not {color.shape}")
        if color.dtype == np.uint8:
            fmt = "rgb8" if color.shape[2] == 3 else "rgba8"
        elif np.issubdtype(color.dtype, np.floating) and color.shape[2] == 3:
            fmt = "rgbf32"
            color = color.astype("<f4", copy=False)
        else:
            raise ValueError(f"color must be uint8 (sRGB) or float RGB (linear), not "
                             f"{color.dtype} x {color.shape[2]}")
        if depth.shape != color.shape[:2]:
            raise ValueError(f"depth is {depth.shape}, color {color.shape[:2]}")
        if depth_units not in _DEPTH_CODES:
            raise ValueError(f"depth_units {depth_units!r}: expected one of {DEPTH_UNITS}")
        depth = depth.astype("<f4", copy=False)
        color = np.ascontiguousarray(color)
        depth = np.ascontiguousarray(depth)
        h, w = depth.shape
        self._seq += 1
        seq = self._seq
        if self._ring is not None:
            slot = seq % self._ring.slots
            self._ring.write(slot, seq, w, h, _COLOR_CODES[fmt], _DEPTH_CODES[depth_units],
                             near, far, app_time_ns, color, depth)
            r = self._request("POST", "/frame", {"slot": slot, "seq": seq}, refused=True)
        else:
            q = {"width": w, "height": h, "color": fmt, "depth": depth_units, "seq": seq}
            for k, v in (("near", near), ("far", far), ("app_time_ns", app_time_ns)):
                if v is not None:
                    q[k] = "inf" if v == float("inf") else v
            body = color.tobytes() + depth.tobytes()
            r = self._request("PUT", "/frame?" + urllib.parse.urlencode(q), body=body,
                              content_type="application/octet-stream", refused=True)
        return int(r["seq"])

    def _send_png(self, color, depth, depth_units, app_time_ns):
        color = np.asarray(color)
        depth = np.asarray(depth, dtype=np.float64)
        if color.dtype != np.uint8 or color.ndim != 3 or color.shape[2] not in (3, 4):
            raise ValueError("encoding='png' takes H x W x 3 or 4 uint8 (sRGB) colour")
        if depth.shape != color.shape[:2]:
            raise ValueError(f"depth is {depth.shape}, color {color.shape[:2]}")
        if depth_units not in ("m", "mm"):
            raise ValueError("encoding='png' sends depth in millimetres: depth_units 'm' or 'mm'")
        mm = depth * 1000.0 if depth_units == "m" else depth
        if np.isnan(mm).any() or (mm <= 0).any():
            raise ValueError("depth must be a distance > 0 (NaN and <= 0 cannot be sent)")
        mm = np.clip(np.rint(mm), 1, 65535).astype(">u2")
        h, w = mm.shape
        colour_png = _png(np.ascontiguousarray(color[:, :, :3]), 2, 8)
        depth_png = _png(np.ascontiguousarray(mm), 0, 16)
        self._seq += 1
        q = {"width": w, "height": h, "color": "png", "color_bytes": len(colour_png),
             "depth": "mm", "seq": self._seq}
        if app_time_ns is not None:
            q["app_time_ns"] = app_time_ns
        r = self._request("PUT", "/frame?" + urllib.parse.urlencode(q),
                          body=colour_png + depth_png,
                          content_type="application/octet-stream", refused=True)
        return int(r["seq"])

    def close(self):
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if self._ring is not None:
            self._ring.close()
            self._ring = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _request(self, method, path, json_body=None, body=None,
                 content_type="application/json", refused=False):
        headers = dict(self._headers)
        if json_body is not None:
            body = json.dumps(json_body).encode()
        if body is not None or method == "POST":
            headers["Content-Type"] = content_type
        for attempt in (0, 1):
            if self._conn is None:
                self._conn = http.client.HTTPConnection(self._host, self._port,
                                                        timeout=self._timeout)
            try:
                self._conn.request(method, path, body=body, headers=headers)
                resp = self._conn.getresponse()
                data = resp.read()
                break
            except (http.client.HTTPException, ConnectionError):
                # The daemon closed a kept-alive connection: once more on a new one.
                self._conn.close()
                self._conn = None
                if attempt:
                    raise
        try:
            v = json.loads(data) if data else {}
        except ValueError:
            v = {"error": data.decode(errors="replace")}
        if resp.status >= 400:
            cls = FrameRefused if refused and resp.status in (409, 413, 422) else DioptraError
            raise cls(resp.status, v.get("error", ""))
        return v


def _png(pixels, color_type: int, bit_depth: int) -> bytes:
    """A PNG of ``pixels`` (H x W x 3 ``uint8`` RGB: colour type 2; H x W big-endian
    ``uint16`` grey: colour type 0), rows unfiltered, zlib-compressed."""
    h, w = pixels.shape[:2]

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))

    rows = pixels.reshape(h, -1).view(np.uint8)
    raw = np.hstack([np.zeros((h, 1), np.uint8), rows]).tobytes()
    ihdr = struct.pack(">IIBBBBB", w, h, bit_depth, color_type, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
            + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))


class _Ring:
    """The daemon's shared-memory ring of frame slots (layout from ``GET /frame/ring``)."""

    def __init__(self, info: dict):
        self._fd = os.open(info["path"], os.O_RDWR)
        try:
            size = os.fstat(self._fd).st_size
            self._map = mmap.mmap(self._fd, size)
        except OSError:
            os.close(self._fd)
            raise
        if self._map[:8] != _MAGIC:
            self.close()
            raise OSError(f"{info['path']} is not a dioptra frame ring")
        self.slots = int(info["slots"])
        self._header = int(info["header_bytes"])
        self._slot_header = int(info["slot_header_bytes"])
        self._slot_bytes = int(info["slot_bytes"])

    def write(self, slot, seq, w, h, color_fmt, depth_kind, near, far, app_time_ns,
              color, depth):
        base = self._header + slot * self._slot_bytes
        cb, db = color.nbytes, depth.nbytes
        if self._slot_header + cb + db > self._slot_bytes:
            raise ValueError(f"a {w}x{h} frame does not fit the ring's slots")
        m = self._map
        # Sequence number 0 while writing, the real one last: the daemon refuses a slot
        # whose number changes while it reads.
        struct.pack_into("<Q", m, base, 0)
        struct.pack_into("<IIffIIQQQ", m, base + 8, color_fmt, depth_kind,
                         float("nan") if near is None else near,
                         float("nan") if far is None else far,
                         w, h, app_time_ns or 0, cb, db)
        start = base + self._slot_header
        m[start:start + cb] = color.tobytes()
        m[start + cb:start + cb + db] = depth.tobytes()
        struct.pack_into("<Q", m, base, seq)

    def close(self):
        try:
            self._map.close()
        finally:
            os.close(self._fd)

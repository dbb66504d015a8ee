"""Frames for a daemon with ``[content] source = "stream"``: the shared-memory ring (its layout
is specified in ``crates/rig/RING.md``), ``PUT /frame`` with raw pixels, and PNG files."""

from __future__ import annotations

import mmap
import os
import struct
import urllib.parse
import zlib
from typing import Optional, Tuple

import numpy as np

from ._http import Http

#: Depth conventions the daemon converts on ingest (a depth buffer needs ``near`` and ``far``).
DEPTH_UNITS = ("m", "mm", "D", "gl", "gl-reversed", "vulkan", "vulkan-reversed", "d3d",
               "d3d-reversed")
DEPTH_CODES = {"m": 1, "D": 2, "gl": 3, "gl-reversed": 4, "vulkan": 5, "vulkan-reversed": 6,
               "d3d": 5, "d3d-reversed": 6, "mm": 7}
COLOR_CODES = {"rgb8": 1, "rgba8": 2, "rgbf32": 3}
#: A slot's ``eye`` (a stereo rig): none (a whole frame), or one eye's half of a pair.
EYE_CODES = {"none": 0, "left": 1, "right": 2}
RING_MAGIC = b"DIOPTRA1"
RING_VERSION = 1
#: A slot header's fields in order (RING.md): name, offset, type.
SLOT_FIELDS = (("seq", 0, "u64"), ("color_format", 8, "u32"), ("depth_kind", 12, "u32"),
               ("near", 16, "f32"), ("far", 20, "f32"), ("width", 24, "u32"),
               ("height", 28, "u32"), ("app_time_ns", 32, "u64"), ("color_bytes", 40, "u64"),
               ("depth_bytes", 48, "u64"), ("eye", 56, "u32"), ("view", 60, "u32"))
_SLOT_FORMAT = "<QIIffIIQQQII"
SLOT_HEADER_BYTES = 64


def pack_slot_header(seq: int, color_format: int, depth_kind: int, near: Optional[float],
                     far: Optional[float], width: int, height: int,
                     app_time_ns: Optional[int], color_bytes: int, depth_bytes: int,
                     eye: int = 0, view: int = 0) -> bytes:
    """A slot header's 64 bytes (``near``/``far`` ``None``: NaN; ``app_time_ns`` ``None``: 0;
    ``eye`` an ``EYE_CODES`` value, 0 for a whole frame; ``view`` 1 + row x N + column for a
    view of an N x N grid, 0 for none)."""
    head = struct.pack(_SLOT_FORMAT, seq, color_format, depth_kind,
                       float("nan") if near is None else near,
                       float("nan") if far is None else far,
                       width, height, app_time_ns or 0, color_bytes, depth_bytes, eye, view)
    return head.ljust(SLOT_HEADER_BYTES, b"\0")


def slot_layout() -> dict:
    """The slot layout as ``GET /frame/ring`` gives it: ``{name: [offset, type]}``."""
    return {name: [offset, kind] for name, offset, kind in SLOT_FIELDS}


class Ring:
    """The daemon's ring of frame slots, mapped into this process."""

    def __init__(self, info: dict):
        if info.get("version") != RING_VERSION or info.get("slot_header") != slot_layout():
            raise OSError(f"the daemon's ring (version {info.get('version')}) has another "
                          f"layout than this client's (version {RING_VERSION})")
        self._fd = os.open(info["path"], os.O_RDWR)
        try:
            self._map = mmap.mmap(self._fd, os.fstat(self._fd).st_size)
        except OSError:
            os.close(self._fd)
            raise
        if self._map[:8] != RING_MAGIC:
            self.close()
            raise OSError(f"{info['path']} is not a dioptra frame ring")
        self.slots = int(info["slots"])
        self._header = int(info["header_bytes"])
        self._slot_bytes = int(info["slot_bytes"])

    def write(self, slot: int, seq: int, header: bytes, color: np.ndarray, depth: np.ndarray):
        """Writes a frame into ``slot``: sequence number 0, the header and pixels, then
        ``seq`` last (the daemon refuses a slot whose number changes while it reads)."""
        base = self._header + slot * self._slot_bytes
        cb, db = color.nbytes, depth.nbytes
        if SLOT_HEADER_BYTES + cb + db > self._slot_bytes:
            raise ValueError("the frame does not fit the ring's slots")
        m = self._map
        struct.pack_into("<Q", m, base, 0)
        m[base + 8:base + SLOT_HEADER_BYTES] = header[8:]
        start = base + SLOT_HEADER_BYTES
        m[start:start + cb] = color.tobytes()
        m[start + cb:start + cb + db] = depth.tobytes()
        struct.pack_into("<Q", m, base, seq)

    def close(self):
        try:
            self._map.close()
        finally:
            os.close(self._fd)


def png(pixels: np.ndarray, color_type: int, bit_depth: int) -> bytes:
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


class FrameSender:
    """Sends frames to one streaming daemon: through the ring when it can be mapped, else
    ``PUT /frame``. Sequence numbers continue after the newest the daemon accepted.

    On a stereo rig a frame may be one eye's half (``eye="left"`` or ``"right"``): the two
    halves of a pair share a sequence number, which the daemon pairs them by.

    Automatic numbers (no ``seq``), the rule:

    - a frame gets the number after the highest this sender used, explicit or automatic (at
      the start, the newest the daemon had accepted);
    - a half takes the number of the open half instead (the other eye's, the last frame this
      sender sent, not yet paired) when no higher number was used since, so an automatic
      number never repeats an older explicit one;
    - a send that raises (the daemon refused it, or it never reached the daemon) uses no
      number: the counter and the open half stay as they were, so a retried half still pairs
      with its partner.

    Light-field content (``content.views = N``): a frame may be N x N views, each sent with
    ``view=(row, column)`` and the frame's ``seq`` (required; :meth:`send_grid` numbers them)."""

    def __init__(self, http: Http, use_ring: bool):
        self._http = http
        ring = http.request("GET", "/frame/ring")  # 409 with the reason unless streaming
        self.width, self.height = int(ring["width"]), int(ring["height"])
        self.ring: Optional[Ring] = None
        if use_ring and ring.get("path"):
            try:
                self.ring = Ring(ring)
            except OSError:
                self.ring = None  # Not on this machine, no permission, another layout.
        self.stereo = bool(ring.get("stereo"))
        self.views = ring.get("views")
        content = http.request("GET", "/status").get("content", {})
        self.seq = int(content.get("newest_seq") or 0)
        # The half sent last, waiting for its partner: (seq, eye).
        self._open_half: Optional[tuple] = None

    def _number(self, eye: Optional[str], seq: Optional[int]) -> Tuple[int, Tuple]:
        """The frame's sequence number (``seq``, its open partner's, or the next) and the
        sender's state (counter, open half) once the daemon has accepted the frame."""
        if eye is not None and eye not in ("left", "right"):
            raise ValueError(f"eye {eye!r}: expected 'left', 'right' or None")
        half = self._open_half
        if seq is None:
            if (eye is not None and half is not None and half[1] != eye
                    and half[0] == self.seq):
                seq = half[0]
            else:
                seq = self.seq + 1
        seq = int(seq)
        if eye is None or (half is not None and half[0] == seq and half[1] != eye):
            open_half = None  # a whole frame, or the pair is complete
        else:
            open_half = (seq, eye)
        return seq, (max(self.seq, seq), open_half)

    def _accepted(self, state: Tuple) -> None:
        """The daemon took the frame: its number is used."""
        self.seq, self._open_half = state

    def _view(self, view, seq) -> Optional[str]:
        """``view`` ``(row, column)`` as ``PUT /frame`` names it (``None``: a whole frame)."""
        if view is None:
            return None
        if seq is None:
            raise ValueError("a view needs its frame's seq (send_grid numbers a grid's views)")
        row, column = (int(x) for x in view)
        return f"{row}_{column}"

    def _view_code(self, view: Optional[str]) -> int:
        """A slot's ``view``: 1 + row x N + column (0: none)."""
        if view is None:
            return 0
        if not self.views:
            raise ValueError("this daemon's content has no view grid (content.views)")
        row, column = (int(x) for x in view.split("_"))
        if not (0 <= row < self.views and 0 <= column < self.views):
            raise ValueError(f"view {view}: the grid is {self.views} x {self.views}")
        return 1 + row * self.views + column

    def send(self, color, depth, depth_units: str, near, far, app_time_ns, encoding,
             eye: Optional[str] = None, seq: Optional[int] = None, view=None) -> int:
        view = self._view(view, seq)
        if view is not None:
            # A grid's view: numbered by the caller (send_grid); the open half stays.
            number, state = int(seq), (max(self.seq, int(seq)), self._open_half)
        else:
            number, state = self._number(eye, seq)
        if encoding == "png":
            r = self._send_png(color, depth, depth_units, app_time_ns, eye, number, view)
        elif encoding == "raw":
            r = self._send_raw(color, depth, depth_units, near, far, app_time_ns, eye, number,
                               view)
        else:
            raise ValueError(f"encoding {encoding!r}: expected 'raw' or 'png'")
        # Only now, after the daemon accepted it (a refusal raised above).
        self._accepted(state)
        return r

    def _send_raw(self, color, depth, depth_units, near, far, app_time_ns, eye, seq,
                  view) -> int:
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
        if depth_units not in DEPTH_CODES:
            raise ValueError(f"depth_units {depth_units!r}: expected one of {DEPTH_UNITS}")
        color = np.ascontiguousarray(color)
        depth = np.ascontiguousarray(depth.astype("<f4", copy=False))
        h, w = depth.shape
        if self.ring is not None:
            # A grid's views share their frame's number: each its own slot, in turn.
            slot = (seq + self._view_code(view)) % self.ring.slots
            header = pack_slot_header(seq, COLOR_CODES[fmt], DEPTH_CODES[depth_units], near,
                                      far, w, h, app_time_ns, color.nbytes, depth.nbytes,
                                      EYE_CODES[eye or "none"], self._view_code(view))
            self.ring.write(slot, seq, header, color, depth)
            r = self._http.request("POST", "/frame", {"slot": slot, "seq": seq}, frame=True)
        else:
            q = {"width": w, "height": h, "color": fmt, "depth": depth_units, "seq": seq}
            for k, v in (("near", near), ("far", far), ("app_time_ns", app_time_ns),
                         ("eye", eye), ("view", view)):
                if v is not None:
                    q[k] = "inf" if v == float("inf") else v
            r = self._http.request("PUT", "/frame?" + urllib.parse.urlencode(q),
                                   body=color.tobytes() + depth.tobytes(),
                                   content_type="application/octet-stream", frame=True)
        return int(r["seq"])

    def _send_png(self, color, depth, depth_units, app_time_ns, eye, seq, view=None) -> int:
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
        colour_png = png(np.ascontiguousarray(color[:, :, :3]), 2, 8)
        depth_png = png(np.ascontiguousarray(mm), 0, 16)
        q = {"width": w, "height": h, "color": "png", "color_bytes": len(colour_png),
             "depth": "mm", "seq": seq}
        if app_time_ns is not None:
            q["app_time_ns"] = app_time_ns
        if eye is not None:
            q["eye"] = eye
        if view is not None:
            q["view"] = view
        r = self._http.request("PUT", "/frame?" + urllib.parse.urlencode(q),
                               body=colour_png + depth_png,
                               content_type="application/octet-stream", frame=True)
        return int(r["seq"])

    def close(self):
        if self.ring is not None:
            self.ring.close()
            self.ring = None

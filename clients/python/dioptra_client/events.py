"""The daemon's live events (``GET /stream``, a WebSocket of JSON messages) as typed objects.

Every event has ``host_ns`` (when it happened, on the daemon's monotonic host clock, ns since
it started; recordings and LSL use the same timeline) and ``wall_ns`` (the daemon's wall clock,
UTC ns, when it sent the message), and ``raw``, the message itself. Fields a daemon does not
send are ``None``.
"""

from __future__ import annotations

import json
import socket
import time
from dataclasses import dataclass
from typing import Any, Iterable, Iterator, Optional, Tuple, Type, Union

from ._http import Http
from .errors import DioptraError


@dataclass(frozen=True)
class Event:
    """A message of a type this client does not know (``type`` says which)."""

    type: str
    host_ns: Optional[int]
    wall_ns: Optional[int]
    raw: dict


@dataclass(frozen=True)
class Eye:
    """One eye of a gaze sample: unit direction (+x right, +y up, +z forward), eye position
    (mm), pupil diameter (mm) and whether the tracker saw it."""

    direction: Tuple[float, float, float]
    valid: bool
    origin_mm: Optional[Tuple[float, float, float]]
    pupil_mm: Optional[float]


@dataclass(frozen=True)
class GazeEvent(Event):
    """A binocular gaze sample. ``host_ns`` is when the eye was seen (the tracker's time on
    the host clock); ``device_ns`` the tracker's own clock; ``phase`` the eye's movement
    (``fixation``, ``saccade``, ``pursuit``, ``blink``, ``lost``, ``unknown``);
    ``vergence_d`` the fused fixation depth (diopters) the scheduler estimates."""

    left: Eye
    right: Eye
    device_ns: Optional[int]
    phase: Optional[str]
    vergence_d: Optional[float]


@dataclass(frozen=True)
class LensEvent(Event):
    """A lens read-back: the power it reports (``power_d``), the power it was last commanded
    (``target_d``) and whether it has settled there (``settled``); ``focus_d`` and
    ``target_focus_d`` are the focus (accommodation demand) those powers give through the
    rig's optics map (equal to the powers when the config has none). ``eye`` is ``left`` or
    ``right`` on a rig with a lens per eye, else ``None``."""

    power_d: float
    target_d: Optional[float]
    settled: Optional[bool]
    focus_d: Optional[float] = None
    target_focus_d: Optional[float] = None
    eye: Optional[str] = None


@dataclass(frozen=True)
class FocusEvent(Event):
    """The scheduler commanded the lens to ``commanded_d`` (``reason``: gaze, manual, ...),
    which gives the focus ``focus_d`` through the optics map; ``eye`` as for
    :class:`LensEvent`."""

    commanded_d: float
    reason: Optional[str]
    focus_d: Optional[float] = None
    eye: Optional[str] = None


@dataclass(frozen=True)
class FrameEvent(Event):
    """A frame (or, multifocal, one layer) went to the display at ``shown_ns``, rendered for
    ``focus_d`` (the layer's plane in multifocal mode)."""

    frame: int
    layer: Optional[int]
    focus_d: Optional[float]
    shown_ns: Optional[int]
    repeat: Optional[bool]


@dataclass(frozen=True)
class SubframeEvent(Event):
    """The sync hardware started a sub-frame: plane ``plane`` at ``plane_d``, with the lens
    measured at ``lens_d`` (``None`` when the hardware does not measure it)."""

    frame: int
    plane: int
    plane_d: Optional[float]
    lens_d: Optional[float]


@dataclass(frozen=True)
class MarkerEvent(Event):
    """A marker posted with ``POST /marker`` (``marker``: its text or JSON object)."""

    marker: Union[str, dict]


@dataclass(frozen=True)
class Lagged(Event):
    """This client read too slowly: the daemon skipped ``skipped`` messages for it."""

    skipped: int


def _eye(v: Any) -> Eye:
    v = v if isinstance(v, dict) else {}
    direction = tuple(v.get("direction") or (0.0, 0.0, 0.0))
    origin = v.get("origin_mm")
    return Eye(direction=direction, valid=bool(v.get("valid")),
               origin_mm=tuple(origin) if origin is not None else None,
               pupil_mm=v.get("pupil_mm"))


def parse_event(msg: Union[str, bytes, dict]) -> Event:
    """One ``/stream`` message (JSON text or a parsed dict) as its typed event."""
    m = json.loads(msg) if isinstance(msg, (str, bytes)) else msg
    kind = str(m.get("type", ""))
    base = dict(type=kind, host_ns=m.get("host_ns"), wall_ns=m.get("wall_ns"), raw=m)
    if kind == "gaze":
        return GazeEvent(**base, left=_eye(m.get("left")), right=_eye(m.get("right")),
                         device_ns=m.get("device_ns"), phase=m.get("phase"),
                         vergence_d=m.get("vergence_d"))
    if kind == "lens":
        return LensEvent(**base, power_d=m.get("power_d"), target_d=m.get("target_d"),
                         settled=m.get("settled"), focus_d=m.get("focus_d"),
                         target_focus_d=m.get("target_focus_d"), eye=m.get("eye"))
    if kind == "focus":
        return FocusEvent(**base, commanded_d=m.get("commanded_d"), reason=m.get("reason"),
                          focus_d=m.get("focus_d"), eye=m.get("eye"))
    if kind == "frame":
        return FrameEvent(**base, frame=m.get("frame"), layer=m.get("layer"),
                          focus_d=m.get("focus_d"), shown_ns=m.get("shown_ns"),
                          repeat=m.get("repeat"))
    if kind == "subframe":
        return SubframeEvent(**base, frame=m.get("frame"), plane=m.get("plane"),
                             plane_d=m.get("plane_d"), lens_d=m.get("lens_d"))
    if kind == "marker":
        return MarkerEvent(**base, marker=m.get("marker"))
    if kind == "lagged":
        return Lagged(**base, skipped=int(m.get("skipped", 0)))
    return Event(**base)


_NAMES = {GazeEvent: "gaze", LensEvent: "lens", FocusEvent: "focus", FrameEvent: "frame",
          SubframeEvent: "subframe", MarkerEvent: "marker", Lagged: "lagged"}


class EventStream(Iterator[Event]):
    """An open ``/stream`` subscription: iterate it for events (from when it opened), or
    call :meth:`next` with a timeout. Close it (or use ``with``) when done."""

    def __init__(self, http: Http, types: Optional[Iterable[Union[str, Type[Event]]]] = None,
                 timeout: Optional[float] = None):
        try:
            import websocket  # websocket-client
        except ImportError as e:
            raise ImportError("events need websocket-client: pip install websocket-client") from e
        self._ws_errors = (websocket.WebSocketException,)
        self._closed_error = websocket.WebSocketConnectionClosedException
        self._timeout_error = websocket.WebSocketTimeoutException
        self._types = None if types is None else {_NAMES.get(t, t) for t in types}
        self._timeout = timeout
        header = [f"{k}: {v}" for k, v in http.headers.items()]
        try:
            if http.kind == "unix":
                sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                sock.settimeout(http.timeout)
                sock.connect(http.where)
                self._ws = websocket.create_connection("ws://localhost/stream", socket=sock,
                                                       header=header, timeout=http.timeout,
                                                       suppress_origin=True)
            else:
                host, port = http.where
                self._ws = websocket.create_connection(f"ws://{host}:{port}/stream",
                                                       header=header, timeout=http.timeout,
                                                       suppress_origin=True)
        except websocket.WebSocketBadStatusException as e:
            raise DioptraError(e.status_code, f"GET /stream: {e}") from e
        except (OSError, websocket.WebSocketException) as e:
            raise DioptraError(None, f"cannot open the event stream at {http.url}: {e}") from e

    def __next__(self) -> Event:
        try:
            return self.next(self._timeout)
        except EOFError:
            raise StopIteration from None

    def next(self, timeout: Optional[float] = None) -> Event:
        """The next event of the chosen types; ``TimeoutError`` after ``timeout`` seconds
        without one, ``EOFError`` when the daemon closed the stream."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            left = None if deadline is None else max(1e-3, deadline - time.monotonic())
            self._ws.settimeout(left)
            try:
                text = self._ws.recv()
            except self._timeout_error:
                raise TimeoutError(f"no event within {timeout} s") from None
            except socket.timeout:
                raise TimeoutError(f"no event within {timeout} s") from None
            except self._closed_error:
                raise EOFError("the daemon closed the event stream") from None
            if not text:
                raise EOFError("the daemon closed the event stream")
            event = parse_event(text)
            if self._types is None or event.type in self._types:
                return event
            if deadline is not None and time.monotonic() >= deadline:
                raise TimeoutError(f"no event of {sorted(self._types)} within {timeout} s")

    def close(self):
        try:
            self._ws.close()
        except (OSError,) + self._ws_errors:
            pass

    def __enter__(self) -> "EventStream":
        return self

    def __exit__(self, *exc):
        self.close()

"""The daemon's whole API from Python: :class:`Dioptra`."""

from __future__ import annotations

import time
from typing import Any, Dict, Iterable, Optional, Type, Union

from ._http import Http
from .errors import DioptraError, NotSettled
from .events import Event, EventStream, LensEvent
from .frames import FrameSender


class Dioptra:
    """A connection to one ``dioptra serve``.

    ``url`` is ``http://host:port`` (the config's ``api.listen``) or ``unix:/path/to.sock``
    (``api.unix``). ``token`` (or ``token_file``, a file holding it) is the config's
    ``api.token``, needed when it sets one. Every call raises :class:`DioptraError` with the
    daemon's reason when the daemon refuses it. Works whatever the rig's content; the frame
    calls (:meth:`send_rgbd`, :attr:`width`, :attr:`height`) need ``[content] source =
    "stream"`` and use the shared-memory ring when the daemon is on this machine
    (``use_ring``), else ``PUT /frame``.

        with Dioptra("http://127.0.0.1:7420") as d:
            d.set_focus(1.5)
            d.wait_settled(timeout=1.0)
            d.marker({"event": "stimulus_on", "trial": 3})
    """

    def __init__(self, url: str = "http://127.0.0.1:7420", token: Optional[str] = None, *,
                 token_file: Optional[str] = None, use_ring: bool = True,
                 timeout: float = 10.0):
        if token is None and token_file is not None:
            with open(token_file, encoding="utf-8") as f:
                token = f.read().strip()
        self._http = Http(url, token, timeout)
        self._use_ring = use_ring
        self._frames: Optional[FrameSender] = None
        # Fails here, with the reason, when no daemon answers at `url`.
        self.status()

    # The rig.

    def status(self) -> Dict[str, Any]:
        """``GET /status``: mode, method, focus, devices, counters, latency, recording."""
        return self._http.request("GET", "/status")

    def set_focus(self, diopters: float) -> float:
        """Manual focus: the lens goes to the focus ``diopters`` (the accommodation demand,
        within what the lens reaches through the optics map: ``status()["focus"]
        ["focus_range_d"]``) and stays there whatever the gaze does, until
        :meth:`release_focus`. Returns the focus the daemon took. Raises
        :class:`DioptraError` (503) while a required lens is down."""
        r = self._http.request("POST", "/focus", {"diopters": float(diopters)})
        return float(r["manual_focus_d"])

    def release_focus(self) -> None:
        """Hands focus back to gaze (ends :meth:`set_focus`)."""
        self._http.request("POST", "/focus", {"diopters": None})

    def set_mode(self, mode: str) -> str:
        """``varifocal``, ``multifocal`` (needs a sync board) or ``lightfield``."""
        return self._http.request("POST", "/mode", {"mode": mode})["mode"]

    def set_method(self, method: str) -> str:
        """A render method that fits the mode (``gather``, ``pyramid``, ``lightfield-defocus``,
        ``linear``, ``optimized``, ``views``, ``network``, ``refine``) or ``auto``."""
        return self._http.request("POST", "/method", {"method": method})["method"]

    def start_recording(self, name: Optional[str] = None, subject: Optional[str] = None,
                        trial: Union[int, str, None] = None) -> str:
        """Starts an MCAP recording in the config's ``recording.dir``; its file name carries
        ``name``, ``subject`` and ``trial`` (letters, digits, ``-``, ``_``, ``.``; a trial may
        be a number). Returns the file's path."""
        body = {k: v for k, v in (("name", name), ("subject", subject), ("trial", trial))
                if v is not None}
        return self._http.request("POST", "/recording/start", body)["recording"]

    def stop_recording(self) -> Dict[str, Any]:
        """Finishes the recording: ``{"path", "messages", "dropped"}``."""
        return self._http.request("POST", "/recording/stop", {})

    def marker(self, marker: Union[str, Dict[str, Any]]) -> int:
        """Marks this moment (a trial's onset, a response): ``marker`` (text, or a JSON
        object) goes into the recording, onto ``/stream`` and to LSL's marker outlet, stamped
        with the daemon's host time when it arrived, which this returns (ns)."""
        if not isinstance(marker, (str, dict)):
            raise TypeError("a marker is a str or a dict")
        return int(self._http.request("POST", "/marker", {"marker": marker})["host_ns"])

    def shutdown(self) -> None:
        """Stops the daemon: parks the lens, finishes files, exits."""
        self._http.request("POST", "/shutdown", {})

    # Events.

    def events(self, types: Optional[Iterable[Union[str, Type[Event]]]] = None,
               timeout: Optional[float] = None) -> EventStream:
        """The daemon's live events from now on, as typed objects (:mod:`.events`):
        ``types`` picks some (``"gaze"`` or :class:`GazeEvent`, ...); iterating waits
        ``timeout`` seconds at most for each (``TimeoutError``). Needs websocket-client.

            with d.events(["gaze"]) as ev:
                samples = [next(ev) for _ in range(250)]
        """
        return EventStream(self._http, types, timeout)

    def wait_settled(self, timeout: float = 2.0, target_d: Optional[float] = None,
                     tolerance_d: float = 1e-3) -> LensEvent:
        """Returns the first lens read-back from now on that reports the lens settled at its
        target; with a lens per eye, once each eye's has (the later one is returned).
        Raises :class:`NotSettled` after ``timeout`` seconds without.

        "Settled" is the daemon's verdict on each read-back (:attr:`LensEvent.settled`): the
        lens's power within the scheduler's ``settled_tolerance_d`` (0.03 D) of the power
        it was commanded to, and the lens not reporting itself moving. ``target_d`` (a focus,
        as given to :meth:`set_focus`) also requires the read-back's target to be that
        focus, within ``tolerance_d``: ``tolerance_d`` compares targets, not the lens's
        power with its target."""
        deadline = time.monotonic() + timeout
        last = None
        focus = self.status().get("focus", {})
        waiting = {e for e in ("left", "right") if e in focus} or {None}
        with self.events(["lens"]) as ev:
            while True:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                try:
                    e = ev.next(left)
                except TimeoutError:
                    break
                last = e
                target = e.target_focus_d if e.target_focus_d is not None else e.target_d
                if e.settled and target is not None and (
                        target_d is None or abs(target - target_d) <= tolerance_d):
                    waiting.discard(e.eye)
                    if not waiting:
                        return e
        where = "" if target_d is None else f" at {target_d} D"
        seen = "" if last is None else (f"; last read-back {last.power_d:.3f} D, target "
                                        f"{last.target_d}, settled {last.settled}")
        raise NotSettled(f"the lens did not report settled{where} within {timeout} s{seen}",
                         last)

    # Frames (a streaming rig).

    def _sender(self) -> FrameSender:
        if self._frames is None:
            self._frames = FrameSender(self._http, self._use_ring)
        return self._frames

    @property
    def width(self) -> int:
        """The display's width: every frame must be this wide."""
        return self._sender().width

    @property
    def height(self) -> int:
        """The display's height."""
        return self._sender().height

    @property
    def uses_ring(self) -> bool:
        """Whether frames go through shared memory (else ``PUT /frame``)."""
        return self._sender().ring is not None

    @property
    def seq(self) -> int:
        """The highest sequence number this client used in a frame the daemon accepted (or
        the newest the daemon had accepted when the client first sent): the next automatic
        number is one more. Setting it starts the numbering over from there."""
        return self._sender().seq

    @seq.setter
    def seq(self, value: int):
        self._sender().seq = int(value)

    def send_rgbd(self, color, depth, depth_units: str = "m", near: Optional[float] = None,
                  far: Optional[float] = None, app_time_ns: Optional[int] = None,
                  encoding: str = "raw", eye: Optional[str] = None,
                  seq: Optional[int] = None, view: Optional[tuple] = None) -> int:
        """Shows one frame; returns its sequence number, or raises :class:`FrameRefused`
        with the daemon's reason (the frame on show stays).

        ``color``: H x W x 3 or 4 ``uint8`` (sRGB), or H x W x 3 float (linear light).
        ``depth``: H x W in ``depth_units`` (see ``DEPTH_UNITS``); a depth buffer (``gl``,
        ``vulkan``, ...) needs ``near`` and ``far`` in metres (``far=float("inf")`` for an
        infinite reversed-Z projection). H x W must be the display's size. ``encoding="png"``
        (``uint8`` colour, depth in ``m`` or ``mm``) sends PNG files through ``PUT /frame``,
        depth in whole millimetres from 1 mm to 65.535 m (farther is sent as 65.535 m).

        A stereo rig (``display.layout`` side-by-side or two-outputs; H x W one eye's image)
        also takes both eyes side by side, H x 2W, and one eye's half of a pair:
        ``eye="left"`` or ``"right"``. The daemon shows a pair once both halves of the same
        sequence number arrived. ``seq`` names the number; without it a frame gets the
        number after the highest this client used (explicit or automatic), and a half the
        number of the half sent last when it is its partner (the other eye) and no higher
        number was used since: ``send_rgbd(l, ld, eye="left")`` then ``send_rgbd(r, rd,
        eye="right")`` is one pair. A refused send (or one that never reached the daemon)
        uses no number, so a corrected half sent again still pairs with its partner. ``eye``
        on a mono rig is refused (:class:`FrameRefused`, 422).

        Light-field content (``content.views = N``): ``view=(row, column)`` with ``seq`` makes
        the frame that view of frame ``seq``'s N x N grid, shown once every view of ``seq``
        arrived (:meth:`send_grid` sends a whole grid).
        """
        return self._sender().send(color, depth, depth_units, near, far, app_time_ns,
                                   encoding, eye, seq, view)

    def send_grid(self, views, depth_units: str = "m", eye: Optional[str] = None,
                  seq: Optional[int] = None, **kwargs) -> int:
        """Shows one frame of light-field content (``content.views = N``): ``views`` is N rows
        of N ``(color, depth)`` pairs, row 0 at the top, column 0 at the left, each as
        :meth:`send_rgbd` takes them. All share one sequence number (``seq``, or the next),
        which is returned; on a stereo rig send each eye's grid with its ``eye`` and the same
        ``seq``. Other keywords go to :meth:`send_rgbd`."""
        sender = self._sender()
        seq = sender.seq + 1 if seq is None else int(seq)
        for r, row in enumerate(views):
            for c, (color, depth) in enumerate(row):
                self.send_rgbd(color, depth, depth_units, eye=eye, seq=seq, view=(r, c),
                               **kwargs)
        return seq

    def close(self) -> None:
        """Closes the connection and unmaps the ring."""
        self._http.close()
        if self._frames is not None:
            self._frames.close()
            self._frames = None

    def __enter__(self) -> "Dioptra":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["Dioptra", "DioptraError", "NotSettled"]

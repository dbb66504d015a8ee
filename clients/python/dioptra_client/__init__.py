"""dioptra_client: drive a ``dioptra serve`` rig from Python.

Focus, mode, method, recordings per trial, markers, live gaze and lens events, and RGB-D
frames for a streaming rig: see :class:`Dioptra`. Plain Python with numpy (and
websocket-client for the live events), so it runs inside PsychoPy or any other experiment
framework.

    from dioptra_client import Dioptra

    with Dioptra("http://127.0.0.1:7420") as d:
        d.start_recording(name="accommodation", subject="s01", trial=1)
        d.set_focus(2.0)
        d.wait_settled(timeout=1.0)
        d.marker("stimulus_on")
        with d.events(["gaze"], timeout=1.0) as ev:
            gaze = [next(ev) for _ in range(250)]
        d.stop_recording()
"""

from ._version import __version__
from .client import Dioptra
from .errors import DioptraError, FrameRefused, NotSettled
from .events import (Event, EventStream, Eye, FocusEvent, FrameEvent, GazeEvent, Lagged,
                     LensEvent, MarkerEvent, SubframeEvent, parse_event)
from .frames import DEPTH_UNITS

__all__ = [
    "__version__", "Dioptra", "DioptraError", "FrameRefused", "NotSettled", "Event",
    "EventStream", "Eye", "FocusEvent", "FrameEvent", "GazeEvent", "Lagged", "LensEvent",
    "MarkerEvent", "SubframeEvent", "parse_event", "DEPTH_UNITS",
]

"""What the client raises."""

from __future__ import annotations

from typing import Optional


class DioptraError(Exception):
    """The daemon refused a request, or could not be reached.

    ``status`` is the HTTP status (``None`` when no answer came), ``message`` the daemon's
    reason (its ``error``) and ``key`` the request field it names, if any.
    """

    def __init__(self, status: Optional[int], message: str, key: Optional[str] = None):
        prefix = f"{status}: " if status is not None else ""
        super().__init__(prefix + message + (f" (key {key!r})" if key else ""))
        self.status = status
        self.message = message
        self.key = key


class FrameRefused(DioptraError):
    """The daemon refused a frame (wrong size, NaN depth, stale sequence number, ...); the
    frame on show stays."""


class NotSettled(DioptraError, TimeoutError):
    """The lens did not report settled at its target within the time allowed."""

    def __init__(self, message: str, last=None):
        super().__init__(None, message)
        #: The last lens event seen (a :class:`LensEvent`), if any.
        self.last = last

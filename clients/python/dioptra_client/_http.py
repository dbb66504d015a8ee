"""One HTTP/1.1 connection to the daemon's API, over TCP or a Unix socket."""

from __future__ import annotations

import http.client
import json
import socket
import urllib.parse
from typing import Any, Dict, Optional, Tuple

from .errors import DioptraError, FrameRefused


class _UnixConnection(http.client.HTTPConnection):
    def __init__(self, path: str, timeout: float):
        # The Host header is not checked on a Unix socket.
        super().__init__("localhost", timeout=timeout)
        self._path = path

    def connect(self):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(self.timeout)
        try:
            s.connect(self._path)
        except OSError:
            s.close()
            raise
        self.sock = s


def parse_url(url: str) -> Tuple[str, Any]:
    """``("tcp", (host, port))`` or ``("unix", path)`` for ``http://host:port`` or
    ``unix:/path/to/dioptra.sock`` (also ``unix:///path``)."""
    if url.startswith("unix:"):
        path = url[len("unix:"):]
        if path.startswith("//"):
            path = path[2:]
        if not path.startswith("/"):
            raise ValueError(f"{url!r}: expected unix:/absolute/path/to/the.sock")
        return "unix", path
    u = urllib.parse.urlparse(url)
    if u.scheme != "http" or not u.hostname:
        raise ValueError(f"{url!r}: expected http://host:port or unix:/path/to/the.sock")
    return "tcp", (u.hostname, u.port or 80)


class Http:
    """Requests to one daemon, on a kept-alive connection (reopened once when the daemon
    closed it while idle)."""

    def __init__(self, url: str, token: Optional[str], timeout: float):
        self.kind, self.where = parse_url(url)
        self.url = url
        self.timeout = timeout
        self.headers: Dict[str, str] = {"Authorization": f"Bearer {token}"} if token else {}
        self._conn: Optional[http.client.HTTPConnection] = None

    def _connection(self) -> http.client.HTTPConnection:
        if self._conn is None:
            if self.kind == "unix":
                self._conn = _UnixConnection(self.where, self.timeout)
            else:
                host, port = self.where
                self._conn = http.client.HTTPConnection(host, port, timeout=self.timeout)
        return self._conn

    def request(self, method: str, path: str, json_body: Any = None, body: bytes = None,
                content_type: str = "application/json", frame: bool = False) -> Any:
        """The answer's JSON; raises :class:`DioptraError` (``FrameRefused`` for a refused
        frame when ``frame``) with the daemon's reason for a 4xx/5xx."""
        headers = dict(self.headers)
        if json_body is not None:
            body = json.dumps(json_body).encode()
        if body is not None or method == "POST":
            headers["Content-Type"] = content_type
        for attempt in (0, 1):
            conn = self._connection()
            try:
                conn.request(method, path, body=body, headers=headers)
                resp = conn.getresponse()
                data = resp.read()
                break
            except (http.client.HTTPException, ConnectionError) as e:
                self.close()
                if attempt:
                    raise DioptraError(None, f"no answer from the daemon at {self.url}: {e}")
            except OSError as e:
                self.close()
                raise DioptraError(None, f"cannot reach the daemon at {self.url}: {e}") from e
        try:
            value = json.loads(data) if data else {}
        except ValueError:
            value = {"error": data.decode(errors="replace")}
        if resp.status >= 400:
            if not isinstance(value, dict):
                value = {"error": str(value)}
            cls = FrameRefused if frame and resp.status in (409, 413, 422) else DioptraError
            raise cls(resp.status, str(value.get("error", "")), value.get("key"))
        return value

    def close(self):
        if self._conn is not None:
            self._conn.close()
            self._conn = None

"""Start and stop a ``dioptra serve`` from Python: for tests, CI checks and dry runs of an
experiment on a simulated rig.

    from dioptra_client.daemon import Daemon, rig_config

    cfg = rig_config("/tmp/run/rig.toml", open("crates/cli/examples/rig-sim.toml").read(),
                     append='[content]\\nsource = "stream"\\n')
    with Daemon("target/debug/dioptra", cfg) as rig:
        d = rig.client()
        ...
    # leaving the block stops it with SIGTERM; rig.exit_code is its exit status

The daemon listens where its config says; ``rig_config`` sets ``api.listen`` to
``127.0.0.1:0`` (a free port) by default, and :class:`Daemon` reads the address from the
daemon's ``API on ...`` line.
"""

from __future__ import annotations

import os
import pathlib
import re
import signal
import subprocess
import threading
import time
from typing import Dict, List, Optional, Union

from .client import Dioptra

_API_LINE = re.compile(r"API on (http://\S+|unix:\S+)")


class DaemonError(RuntimeError):
    """The daemon did not start (its log is in ``log``), or did not stop."""

    def __init__(self, message: str, log: str = ""):
        super().__init__(message + (f"\n--- its log ---\n{log}" if log else ""))
        self.log = log


def rig_config(path: Union[str, pathlib.Path], base: str, *, listen: str = "127.0.0.1:0",
               recording_dir: Union[str, pathlib.Path, None] = None,
               replace: Optional[Dict[str, str]] = None, append: str = "") -> pathlib.Path:
    """Writes a rig config to ``path``: the text ``base`` (e.g. the example rig's), its
    ``api.listen`` set to ``listen``, its ``recording.dir`` to ``recording_dir`` (default:
    ``rec`` beside ``path``), each ``old -> new`` of ``replace`` applied (each ``old`` must be
    in it), and ``append`` added (more sections)."""
    path = pathlib.Path(path)
    text = base
    edits = dict(replace or {})
    rec = pathlib.Path(recording_dir) if recording_dir is not None else path.parent / "rec"
    text = re.sub(r'(?m)^listen = "[^"]*"', f'listen = "{listen}"', text, count=1)
    text = re.sub(r'(?m)^dir = "[^"]*"', f'dir = "{rec}"', text, count=1)
    for old, new in edits.items():
        if old not in text:
            raise ValueError(f"{old!r} is not in the base config")
        text = text.replace(old, new)
    if append:
        text += "\n" + append
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


class Daemon:
    """A ``dioptra serve --config CONFIG`` process (``binary`` is the ``dioptra`` executable).

    :meth:`start` returns once the API listens (its address in :attr:`url`); the daemon's
    stderr is kept in :attr:`log`. :meth:`stop` sends SIGTERM and returns the exit status.
    """

    def __init__(self, binary: Union[str, pathlib.Path], config: Union[str, pathlib.Path], *,
                 args: Optional[List[str]] = None, env: Optional[Dict[str, str]] = None,
                 cwd: Union[str, pathlib.Path, None] = None, start_timeout: float = 120.0):
        self.binary = str(binary)
        self.config = str(config)
        self.args = list(args or [])
        self.env = env
        self.cwd = cwd
        self.start_timeout = start_timeout
        self.url: Optional[str] = None
        self.log: List[str] = []
        self.exit_code: Optional[int] = None
        self.proc: Optional[subprocess.Popen] = None
        self._reader: Optional[threading.Thread] = None
        self._listening = threading.Event()

    @property
    def pid(self) -> int:
        assert self.proc is not None, "not started"
        return self.proc.pid

    def start(self) -> "Daemon":
        env = None if self.env is None else {**os.environ, **self.env}
        self.proc = subprocess.Popen(
            [self.binary, "serve", "--config", self.config, *self.args],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
            cwd=self.cwd)
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        deadline = time.monotonic() + self.start_timeout
        while not self._listening.wait(0.05):
            if self.proc.poll() is not None:
                self._reader.join(5)
                self.exit_code = self.proc.returncode
                raise DaemonError(f"dioptra serve exited ({self.exit_code}) before it listened",
                                  self.log_text())
            if time.monotonic() > deadline:
                self.kill()
                raise DaemonError(f"dioptra serve did not listen within {self.start_timeout} s",
                                  self.log_text())
        return self

    def _read(self):
        assert self.proc is not None and self.proc.stderr is not None
        for line in self.proc.stderr:
            self.log.append(line)
            if self.url is None:
                m = _API_LINE.search(line)
                if m:
                    self.url = m.group(1)
                    self._listening.set()

    def log_text(self) -> str:
        return "".join(self.log)

    def client(self, **kwargs) -> Dioptra:
        """A :class:`Dioptra` connected to this daemon."""
        assert self.url is not None, "not started"
        return Dioptra(self.url, **kwargs)

    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def signal(self, sig: int = signal.SIGTERM):
        assert self.proc is not None, "not started"
        self.proc.send_signal(sig)

    def wait(self, timeout: float = 30.0) -> int:
        """Waits for the daemon to exit; its exit status (``DaemonError`` if it does not)."""
        assert self.proc is not None, "not started"
        try:
            self.exit_code = self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            raise DaemonError(f"dioptra serve did not exit within {timeout} s",
                              self.log_text()) from None
        if self._reader is not None:
            self._reader.join(5)
        return self.exit_code

    def stop(self, timeout: float = 30.0) -> int:
        """SIGTERM (park the lens, finish files, exit), then :meth:`wait`."""
        if self.proc is None:
            raise DaemonError("not started")
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        return self.wait(timeout)

    def kill(self):
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.exit_code = self.proc.wait()

    def __enter__(self) -> "Daemon":
        return self.start() if self.proc is None else self

    def __exit__(self, *exc):
        if self.running():
            self.stop()

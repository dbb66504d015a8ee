"""Fixtures: a real ``dioptra serve`` on the example rig (simulated devices), started and
stopped with :mod:`dioptra_client.daemon`, the code the CI check scripts use too.

The binary is ``--dioptra PATH``, else ``$DIOPTRA_BIN``, else ``target/debug/dioptra`` in the
repository (``cargo build -p dioptra`` makes it). Run from the repository root or anywhere:

    pip install ./clients/python pytest
    python3 -m pytest clients/python/tests
"""

from __future__ import annotations

import os
import pathlib

import pytest

from dioptra_client.daemon import Daemon, rig_config

ROOT = pathlib.Path(__file__).resolve().parents[3]
EXAMPLE_RIG = ROOT / "crates/cli/examples/rig-sim.toml"
GOLDEN = ROOT / "crates/rig/ring-golden.json"


def pytest_addoption(parser):
    parser.addoption("--dioptra", default=None,
                     help="the dioptra binary (default $DIOPTRA_BIN, else target/debug/dioptra)")


@pytest.fixture(scope="session")
def binary(request) -> pathlib.Path:
    b = (request.config.getoption("--dioptra") or os.environ.get("DIOPTRA_BIN")
         or ROOT / "target/debug/dioptra")
    b = pathlib.Path(b)
    if not b.exists():
        pytest.fail(f"{b} does not exist: cargo build -p dioptra, or pass --dioptra PATH")
    return b


@pytest.fixture(scope="session")
def example_rig() -> str:
    return EXAMPLE_RIG.read_text()


class Rigs:
    """Starts daemons on variants of the example rig; stops each at the end of the test (or
    module) and checks it exited 0 on SIGTERM."""

    def __init__(self, binary: pathlib.Path, base: str, tmp: pathlib.Path):
        self.binary, self.base, self.tmp = binary, base, tmp
        self.started = []

    def start(self, *, content: str = "", append: str = "", replace=None,
              listen: str = "127.0.0.1:0", env=None) -> Daemon:
        """A daemon on the example rig; ``content`` is a ``[content]`` source (``stream``,
        ``files``, ...; default the procedural scene)."""
        d = self.tmp / f"rig{len(self.started)}"
        extra = append
        if content:
            extra = f'[content]\nsource = "{content}"\n' + extra
        cfg = rig_config(d / "rig.toml", self.base, listen=listen, replace=replace,
                         append=extra)
        rig = Daemon(self.binary, cfg, env=env)
        self.started.append(rig)
        return rig.start()

    def stop_all(self):
        codes = []
        for rig in self.started:
            if rig.proc is not None and rig.exit_code is None:
                codes.append((rig, rig.stop()))
        bad = [(r.config, c, r.log_text()[-2000:]) for r, c in codes if c != 0]
        assert not bad, f"daemons exited non-zero on SIGTERM: {bad}"


@pytest.fixture
def rigs(binary, example_rig, tmp_path):
    r = Rigs(binary, example_rig, tmp_path)
    yield r
    r.stop_all()


@pytest.fixture(scope="module")
def module_rigs(binary, example_rig, tmp_path_factory):
    r = Rigs(binary, example_rig, tmp_path_factory.mktemp("rigs"))
    yield r
    r.stop_all()


@pytest.fixture(scope="module")
def scene_rig(module_rigs) -> Daemon:
    """The example rig as it ships: the procedural scene, simulated devices."""
    return module_rigs.start()


@pytest.fixture(scope="module")
def stream_rig(module_rigs) -> Daemon:
    """The example rig showing frames a client streams."""
    return module_rigs.start(content="stream")


@pytest.fixture
def client(scene_rig):
    with scene_rig.client() as d:
        yield d

"""The package as pip installs it: its version follows the workspace's, its README exists."""

import re

import dioptra_client
from conftest import ROOT


def test_version_follows_the_workspace():
    cargo = (ROOT / "Cargo.toml").read_text()
    section = cargo.split("[workspace.package]", 1)[1]
    want = re.search(r'(?m)^version = "([^"]+)"', section).group(1)
    assert dioptra_client.__version__ == want


def test_the_readme_pyproject_names_exists():
    pyproject = (ROOT / "clients/python/pyproject.toml").read_text()
    readme = re.search(r'(?m)^readme = "([^"]+)"', pyproject).group(1)
    assert (ROOT / "clients/python" / readme).is_file()


def test_every_public_call_has_a_docstring():
    from dioptra_client import Dioptra
    public = [n for n in dir(Dioptra) if not n.startswith("_")]
    assert {"status", "set_focus", "release_focus", "set_mode", "set_method",
            "start_recording", "stop_recording", "marker", "events", "wait_settled",
            "send_rgbd"} <= set(public)
    missing = [n for n in public if not getattr(Dioptra, n).__doc__]
    assert not missing, missing

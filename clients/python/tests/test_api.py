"""Every call of the client against a real daemon on the example (simulated) rig, the errors
it raises with the daemon's reasons, and token and Unix-socket connections."""

import pathlib
import time

import pytest

from dioptra_client import (Dioptra, DioptraError, FocusEvent, FrameEvent, GazeEvent,
                            LensEvent, MarkerEvent, NotSettled)


def eventually(what, check, timeout=20.0):
    """Polls ``check`` until it returns something true; fails naming ``what`` after
    ``timeout`` s (a deadline for a real daemon, not a timing assertion)."""
    deadline = time.monotonic() + timeout
    while True:
        v = check()
        if v:
            return v
        if time.monotonic() > deadline:
            pytest.fail(f"{what}: not within {timeout} s (last {v!r})")
        time.sleep(0.05)


def test_status(client):
    s = client.status()
    assert s["mode"] == "varifocal"
    assert s["content"]["source"] == "scene"
    assert s["devices"]["lens"]["state"] in ("connecting", "ok")


def test_manual_focus_and_back_to_gaze(client):
    assert client.set_focus(1.5) == 1.5
    assert client.status()["focus"]["manual_d"] == 1.5
    eventually("the lens commanded to 1.5 D",
               lambda: abs((client.status()["focus"]["commanded_d"] or 0) - 1.5) < 1e-4)
    client.release_focus()
    assert client.status()["focus"]["manual_d"] is None


def test_refusals_carry_the_daemons_reason_and_key(client):
    with pytest.raises(DioptraError) as e:
        client.set_focus(40.0)
    assert e.value.status == 422 and e.value.key == "diopters"
    assert "optics.lens_range" in e.value.message
    with pytest.raises(DioptraError) as e:
        client.set_mode("holographic")
    assert e.value.status == 422 and e.value.key == "mode"
    with pytest.raises(DioptraError) as e:
        client.set_method("linear")  # a multifocal method in varifocal mode
    assert e.value.status == 409
    with pytest.raises(DioptraError) as e:
        client.start_recording(subject="s 01")
    assert e.value.status == 422 and e.value.key == "subject"
    with pytest.raises(DioptraError) as e:
        client.stop_recording()
    assert e.value.status == 409 and "not recording" in e.value.message
    with pytest.raises(TypeError):
        client.marker(3)


def test_modes_and_methods(client):
    try:
        assert client.set_mode("lightfield") == "lightfield"
        assert client.set_method("views") == "views"
        assert client.set_mode("varifocal") == "varifocal"
        assert client.set_method("lightfield-defocus") == "lightfield-defocus"
        assert client.set_method("auto") == "auto"
        assert client.status()["method"] == "auto"
    finally:
        client.set_mode("varifocal")
        client.set_method("gather")


def test_a_recording_per_trial(client):
    path = client.start_recording(name="accommodation", subject="s01", trial=3)
    assert path.endswith("-accommodation-sub-s01-trial-3.mcap"), path
    time.sleep(0.3)
    stats = client.stop_recording()
    assert stats["path"] == path and stats["messages"] > 0
    assert pathlib.Path(path).stat().st_size > 0


def test_live_events_are_typed(client):
    with client.events(timeout=10.0) as ev:
        seen = {}
        for e in ev:
            seen.setdefault(type(e), e)
            if {GazeEvent, LensEvent, FrameEvent} <= set(seen):
                break
        g = seen[GazeEvent]
        assert isinstance(g.host_ns, int) and len(g.left.direction) == 3
        assert isinstance(g.left.valid, bool)
        assert isinstance(seen[LensEvent].power_d, float)
    with client.events([FocusEvent], timeout=10.0) as ev:
        client.set_focus(2.0)
        # Gaze may command the lens between the subscription and the manual focus.
        f = next(e for e in ev if e.reason == "manual")
        assert isinstance(f, FocusEvent) and abs(f.commanded_d - 2.0) < 1e-4
    client.release_focus()
    with client.events(["frame"], timeout=10.0) as ev:
        f = next(ev)
        assert isinstance(f, FrameEvent) and f.frame >= 0 and f.focus_d is not None


def test_full_gaze_on_the_stream(client):
    with client.events(["gaze"], timeout=10.0) as ev:
        g = next(ev)
    assert isinstance(g, GazeEvent)
    for eye in (g.left, g.right):
        assert len(eye.direction) == 3 and len(eye.origin_mm) == 3
        assert 1.0 < eye.pupil_mm < 9.0
    assert g.phase in ("fixation", "saccade", "pursuit", "blink", "lost", "unknown")
    assert isinstance(g.device_ns, int) and isinstance(g.wall_ns, int)
    assert g.vergence_d is None or isinstance(g.vergence_d, float)


def test_wait_settled_returns_the_settled_read_back_at_the_target(client):
    try:
        client.set_focus(2.5)
        e = client.wait_settled(timeout=10.0, target_d=2.5)
        assert isinstance(e, LensEvent) and e.settled is True
        # Settled means within the scheduler's settled tolerance, 0.03 D.
        assert e.target_d == 2.5 and abs(e.power_d - 2.5) <= 0.03
        assert client.status()["focus"]["lens_settled"] is True
        # A target the lens was never sent to: no settled read-back there, NotSettled.
        with pytest.raises(NotSettled) as err:
            client.wait_settled(timeout=0.5, target_d=3.9)
        assert "3.9" in str(err.value) and err.value.last is not None
        assert isinstance(err.value, TimeoutError)
    finally:
        client.release_focus()


def test_markers_are_streamed_recorded_and_stamped(client, binary):
    import json
    import subprocess
    path = client.start_recording(name="markers", trial=1)
    with client.events([MarkerEvent], timeout=10.0) as ev:
        t1 = client.marker("stimulus_on")
        t2 = client.marker({"event": "response", "key": "left", "rt_ms": 412})
        m1, m2 = next(ev), next(ev)
    client.stop_recording()
    assert (m1.marker, m1.host_ns) == ("stimulus_on", t1)
    assert (m2.marker, m2.host_ns) == ({"event": "response", "key": "left", "rt_ms": 412}, t2)
    assert t2 >= t1
    out = subprocess.run([str(binary), "replay", "--json", path], capture_output=True,
                         text=True, timeout=120)
    assert json.loads(out.stdout)["topics"]["/marker"] == 2, out.stderr
    for bad in ("", "x" * 1025):
        with pytest.raises(DioptraError) as e:
            client.marker(bad)
        assert e.value.status == 422 and e.value.key == "marker"


def test_the_lens_stream_carries_target_and_settled(client):
    with client.events(["lens"], timeout=10.0) as ev:
        client.set_focus(1.0)
        try:
            for e in ev:
                assert isinstance(e, LensEvent) and isinstance(e.power_d, float)
                if e.target_d == 1.0 and e.settled:
                    break
        finally:
            client.release_focus()


def test_frame_calls_need_a_streaming_rig(client):
    with pytest.raises(DioptraError) as e:
        client.width
    assert e.value.status == 409 and 'source = "stream"' in e.value.message


def test_no_daemon_is_a_clear_error():
    with pytest.raises(DioptraError) as e:
        Dioptra("http://127.0.0.1:9", timeout=2.0)
    assert e.value.status is None and "127.0.0.1:9" in str(e.value)
    with pytest.raises(ValueError):
        Dioptra("ftp://example.org")


TOKEN = "0123456789abcdef0123"


def test_a_token(rigs, tmp_path):
    rig = rigs.start(replace={'listen = "127.0.0.1:0"':
                              f'listen = "127.0.0.1:0"\ntoken = "{TOKEN}"'})
    with pytest.raises(DioptraError) as e:
        rig.client()
    assert e.value.status == 401
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    for d in (rig.client(token=TOKEN), rig.client(token_file=str(token_file))):
        with d:
            assert d.status()["mode"] == "varifocal"
            with d.events(["gaze"], timeout=10.0) as ev:
                assert isinstance(next(ev), GazeEvent)


def test_a_unix_socket(rigs, tmp_path):
    sock = tmp_path / "dioptra.sock"
    rig = rigs.start(content="stream",
                     replace={'listen = "127.0.0.1:0"': f'unix = "{sock}"'})
    assert rig.url == f"unix:{sock}"
    with rig.client() as d:
        assert d.status()["content"]["source"] == "stream"
        with d.events(["gaze"], timeout=10.0) as ev:
            assert isinstance(next(ev), GazeEvent)
        # The ring lies beside the socket; frames go through it.
        assert d.uses_ring
        import numpy as np
        seq = d.send_rgbd(np.zeros((d.height, d.width, 3), np.uint8),
                          np.ones((d.height, d.width), np.float32))
        assert seq >= 1


def test_wait_settled_waits_for_each_eyes_lens(binary, tmp_path):
    """On a rig with a lens per eye, wait_settled returns once both lenses report settled at
    the focus, and lens events say which eye."""
    from conftest import ROOT, Rigs
    rigs = Rigs(binary, (ROOT / "crates/cli/examples/rig-sim-binocular.toml").read_text(),
                tmp_path)
    try:
        with rigs.start().client() as d:
            d.set_focus(1.5)
            e = d.wait_settled(timeout=10.0, target_d=1.5)
            assert e.settled and e.eye in ("left", "right")
            focus = d.status()["focus"]
            for eye in ("left", "right"):
                # Settled: within the scheduler's settled tolerance, 0.03 D.
                assert abs(focus[eye]["lens_focus_d"] - 1.5) <= 0.03, focus
            d.release_focus()
    finally:
        rigs.stop_all()

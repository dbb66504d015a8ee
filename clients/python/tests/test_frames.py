"""Frames to a streaming rig: through the ring, PUT /frame and PNG files, and each refusal
with its reason (the frame on show stays)."""

import numpy as np
import pytest

from dioptra_client import FrameRefused


def frame(d, k):
    return (np.full((d.height, d.width, 3), k % 256, np.uint8),
            np.full((d.height, d.width), 0.25 + (k % 8) * 0.25, np.float32))


@pytest.fixture
def ring_client(stream_rig):
    with stream_rig.client() as d:
        yield d


@pytest.fixture
def put_client(stream_rig):
    with stream_rig.client(use_ring=False) as d:
        yield d


def test_frames_through_the_ring(ring_client):
    d = ring_client
    assert d.uses_ring
    before = d.status()["content"]["received"]
    seqs = [d.send_rgbd(*frame(d, k)) for k in range(20)]
    assert seqs == sorted(seqs) and len(set(seqs)) == 20
    st = d.status()["content"]
    assert st["received"] == before + 20 and st["newest_seq"] == seqs[-1]


def test_frames_through_put_raw_and_png(put_client, ring_client):
    d = put_client
    assert not d.uses_ring
    d.seq = ring_client.status()["content"]["newest_seq"]
    a = d.send_rgbd(*frame(d, 1))
    color, depth = frame(d, 2)
    b = d.send_rgbd(color, depth, encoding="png")
    c = d.send_rgbd(color.astype(np.float32) / 255.0, 1.0 / depth, depth_units="D")
    assert a < b < c == d.status()["content"]["newest_seq"]


def test_refusals_are_counted_and_leave_the_frame_on_show(ring_client):
    d = ring_client
    color, depth = frame(d, 3)
    d.send_rgbd(color, depth)
    newest = d.status()["content"]["newest_seq"]
    cases = [
        ("wrong_size", 422, lambda: d.send_rgbd(color[:-1], depth[:-1])),
        ("depth", 422, lambda: d.send_rgbd(color, np.where(depth > 0, np.nan, depth))),
        ("invalid", 422, lambda: d.send_rgbd(color, depth * 0 + 0.5, depth_units="vulkan")),
        ("depth", 422, lambda: d.send_rgbd(color, -depth)),
    ]
    for kind, status, send in cases:
        n = d.status()["content"]["refused"].get(kind, 0)
        with pytest.raises(FrameRefused) as e:
            send()
        assert e.value.status == status and e.value.message
        assert d.status()["content"]["refused"].get(kind, 0) == n + 1, kind
    # A client that starts its numbers over.
    d.seq = 0
    with pytest.raises(FrameRefused) as e:
        d.send_rgbd(color, depth)
    assert e.value.status == 409 and "not newer" in e.value.message
    assert d.status()["content"]["newest_seq"] == newest


def test_bad_arrays_are_refused_before_sending(ring_client):
    d = ring_client
    color, depth = frame(d, 4)
    with pytest.raises(ValueError):
        d.send_rgbd(color[:, :, :2], depth)
    with pytest.raises(ValueError):
        d.send_rgbd(color, depth, depth_units="furlongs")
    with pytest.raises(ValueError):
        d.send_rgbd(color, depth, encoding="jpeg")
    with pytest.raises(ValueError):
        d.send_rgbd(color, depth, depth_units="D", encoding="png")


@pytest.fixture(scope="module")
def stereo_rig(binary, tmp_path_factory):
    """The binocular example rig (side by side, 96 x 96 per eye) showing streamed frames."""
    from conftest import ROOT, Rigs
    rigs = Rigs(binary, (ROOT / "crates/cli/examples/rig-sim-binocular.toml").read_text(),
                tmp_path_factory.mktemp("stereo"))
    yield rigs.start(content="stream")
    rigs.stop_all()


@pytest.mark.parametrize("use_ring", [True, False])
def test_stereo_halves_pair_up_by_sequence_number(stereo_rig, use_ring):
    """Each eye's half through the ring or PUT: the second takes the first's number, and the
    pair is shown once both are in; both eyes side by side in one frame; a lone half waits."""
    with stereo_rig.client(use_ring=use_ring) as d:
        assert d.uses_ring == use_ring
        color, depth = frame(d, 1)
        before = d.status()["content"]
        a = d.send_rgbd(color, depth, eye="left")
        st = d.status()["content"]
        assert st["stereo"] and st["halves_waiting"] == 1 and st["received"] == before["received"]
        assert d.send_rgbd(color + 1, depth, eye="right") == a
        st = d.status()["content"]
        assert st["received"] == before["received"] + 1 and st["halves_waiting"] == 0
        # Both eyes side by side: H x 2W, no eye.
        b = d.send_rgbd(np.hstack([color, color]), np.hstack([depth, depth]))
        assert b == a + 1
        # PNG files too, numbered explicitly.
        assert d.send_rgbd(color, depth, encoding="png", eye="right", seq=b + 1) == b + 1
        assert d.send_rgbd(color, depth, encoding="png", eye="left") == b + 1
        st = d.status()["content"]
        assert st["received"] == before["received"] + 3, st
        assert st["halves_received"] == before["halves_received"] + 4, st
        # A half of the wrong size, and a pair already shown: refused with the reason.
        with pytest.raises(FrameRefused) as e:
            d.send_rgbd(np.hstack([color, color]), np.hstack([depth, depth]), eye="left")
        assert e.value.status == 422 and "one eye's image" in e.value.message
        with pytest.raises(FrameRefused) as e:
            d.send_rgbd(color, depth, eye="left", seq=b)
        assert e.value.status == 409 and "left eye's sequence number" in e.value.message
        with pytest.raises(ValueError):
            d.send_rgbd(color, depth, eye="cyclops")


@pytest.mark.parametrize("use_ring", [True, False])
def test_a_refused_half_uses_no_sequence_number(stereo_rig, use_ring):
    """The lab's case: a left half takes n, a right half of the wrong size is refused (422),
    the corrected right half sent again takes n too and completes the pair."""
    with stereo_rig.client(use_ring=use_ring) as d:
        color, depth = frame(d, 2)
        before = d.status()["content"]
        n = d.send_rgbd(color, depth, eye="left")
        with pytest.raises(FrameRefused) as e:
            d.send_rgbd(color[:-1], depth[:-1], eye="right")
        assert e.value.status == 422
        assert d.seq == n
        assert d.send_rgbd(color, depth, eye="right") == n
        st = d.status()["content"]
        assert st["received"] == before["received"] + 1 and st["halves_waiting"] == 0, st
        assert st["newest_seq"] == n
        # A refused whole frame uses none either: the next one takes the number after n.
        wide = (np.hstack([color, color]), np.hstack([depth, depth]))
        with pytest.raises(FrameRefused):
            d.send_rgbd(color[:-1], depth[:-1])
        assert d.send_rgbd(*wide) == n + 1


def test_explicit_and_automatic_numbers_do_not_collide(stereo_rig):
    """Automatic numbers continue after the highest used, explicit or automatic; a half
    joins the open half only while nothing higher was used."""
    with stereo_rig.client() as d:
        color, depth = frame(d, 3)
        n = d.send_rgbd(color, depth, eye="left")
        assert d.send_rgbd(color, depth, eye="right") == n
        # An explicit number below the newest pair: refused (409), and it leaves nothing
        # behind: the next automatic half is new, not the refused one's (that was a 409 too).
        with pytest.raises(FrameRefused) as e:
            d.send_rgbd(color, depth, eye="left", seq=n - 1)
        assert e.value.status == 409
        m = d.send_rgbd(color, depth, eye="right")
        assert m == n + 1
        assert d.send_rgbd(color, depth, eye="left") == m
        # An explicit number ahead of the counter: the partner shares it, then numbering
        # continues after it.
        k = m + 10
        assert d.send_rgbd(color, depth, eye="left", seq=k) == k
        assert d.send_rgbd(color, depth, eye="right") == k
        assert d.send_rgbd(color, depth, eye="left") == k + 1
        # A lone half accepted out of order (explicit, below the counter) is not joined by
        # an automatic half: that takes a new number.
        assert d.send_rgbd(color, depth, eye="right", seq=k + 5) == k + 5
        assert d.send_rgbd(color, depth, eye="left", seq=k + 3) == k + 3
        assert d.send_rgbd(color, depth, eye="right") == k + 6
        assert d.status()["content"]["halves_waiting"] >= 1


def test_an_eye_on_a_mono_rig_is_refused(ring_client):
    d = ring_client
    color, depth = frame(d, 5)
    with pytest.raises(FrameRefused) as e:
        d.send_rgbd(color, depth, eye="left")
    assert e.value.status == 422 and 'display.layout = "one"' in e.value.message


@pytest.mark.parametrize("use_ring", [True, False])
def test_a_light_field_grid_is_shown_once_every_view_arrived(rigs, use_ring):
    """Light-field content (``content.views = 2``): a grid's four views share a sequence number
    and the frame counts once, when the last arrives; a lone view waits; a view outside the
    grid, or without its frame's number, is refused with the reason."""
    rig = rigs.start(content="stream", append="views = 2\n")
    with rig.client(use_ring=use_ring) as d:
        assert d.uses_ring == use_ring
        before = d.status()["content"]
        assert before["views"] == 2
        grid = [[frame(d, 10 * r + c) for c in range(2)] for r in range(2)]
        seq = d.send_grid(grid)
        st = d.status()["content"]
        assert st["received"] == before["received"] + 1 and st["newest_seq"] == seq, st
        assert st["views_received"] == before["views_received"] + 4, st
        assert st["halves_waiting"] == 0, st
        # One view of the next frame: it waits for the other three.
        d.send_rgbd(*frame(d, 1), seq=seq + 1, view=(1, 0))
        st = d.status()["content"]
        assert st["halves_waiting"] == 1 and st["received"] == before["received"] + 1, st
        # The same view again: stale (409).
        with pytest.raises(FrameRefused) as e:
            d.send_rgbd(*frame(d, 1), seq=seq + 1, view=(1, 0))
        assert e.value.status == 409 and "view 2" in e.value.message
        with pytest.raises(ValueError):
            d.send_rgbd(*frame(d, 1), view=(0, 0))
        if use_ring:
            with pytest.raises(ValueError):
                d.send_rgbd(*frame(d, 1), seq=seq + 1, view=(2, 0))
        else:
            with pytest.raises(FrameRefused) as e:
                d.send_rgbd(*frame(d, 1), seq=seq + 1, view=(2, 0))
            assert e.value.status == 422 and "content.views = 2" in e.value.message


def test_a_view_on_a_rig_without_a_grid_is_refused(put_client):
    d = put_client
    with pytest.raises(FrameRefused) as e:
        d.send_rgbd(*frame(d, 1), seq=10_000, view=(0, 0))
    assert e.value.status == 422 and "content.views" in e.value.message

"""The example experiment (examples/experiment.py) runs a session against a real daemon,
streamed or with the rig's own content, and each trial's recording holds its markers."""

import csv
import json
import pathlib
import subprocess
import sys

import pytest

EXAMPLE = pathlib.Path(__file__).resolve().parents[1] / "examples" / "experiment.py"


def recorded_topics(binary, path):
    """Messages per topic of a recording, as ``dioptra replay --json`` counts them."""
    out = subprocess.run([str(binary), "replay", "--json", path], capture_output=True,
                         text=True, timeout=120)
    assert out.stdout, out.stderr
    return json.loads(out.stdout)["topics"]


@pytest.mark.parametrize("content", ["scene", "stream"])
def test_the_example_experiment_runs_a_session(rigs, binary, tmp_path, content):
    rig = rigs.start(content=content)
    out = tmp_path / "trials.csv"
    # Run from another directory: the example finds its neighbour module itself.
    r = subprocess.run([sys.executable, str(EXAMPLE), "--url", rig.url, "--subject", "s07",
                        "--depths", "0.5,2.0", "--gaze-s", "0.3", "--out", str(out)],
                       capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    rows = list(csv.DictReader(open(out)))
    assert [(row["trial"], row["depth_m"]) for row in rows] == [("1", "0.5"), ("2", "2.0")]
    for row in rows:
        assert row["recording"].endswith(f"-accommodation-sub-s07-trial-{row['trial']}.mcap")
        assert int(row["gaze_samples"]) > 10
        assert 0.0 < float(row["pupil_mm"]) < 10.0
        assert row["settled_ns"] and int(row["onset_ns"]) >= int(row["settled_ns"])
        topics = recorded_topics(binary, row["recording"])
        assert topics.get("/marker") == 3, topics
        assert topics.get("/gaze", 0) > 10, topics
    # Focus went back to gaze at the end.
    with rig.client() as d:
        assert d.status()["focus"]["manual_d"] is None
        if content == "stream":
            assert d.status()["content"]["received"] == 2

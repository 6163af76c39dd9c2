"""Tracking through the real worker processes (grabber .. cca, tracking, recorder over
zenoh) on a short simulated meeting, scored by ``smartroom eval`` against ground truth."""
import json

import pytest

from tests.conftest import simulated, smartroom

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def meeting(tmp_path_factory):
    return simulated(tmp_path_factory, "meeting3", 5)


def test_run_writes_tracks_that_score_against_ground_truth(meeting, tmp_path):
    out = tmp_path / "out"
    r = smartroom("run", "--recording", meeting, "--headless", "--no-pace", "--out", out, timeout=300)
    assert r.returncode == 0, r.stderr
    stats = json.loads((out / "stats.json").read_text())
    assert stats["stages"]["tracking"]["frames_out"] >= 110
    lines = (out / "tracks.jsonl").read_text().splitlines()
    assert len(lines) >= 110
    r = smartroom("eval", "--recording", meeting, "--results", out)
    assert r.returncode == 0, r.stderr
    s = json.loads((out / "eval.json").read_text())["tracking"]
    assert s["frames"] >= 110
    # the people present from the first frame, one entering at 2.7 s
    assert s["mota"] >= 0.85 and s["idf1"] >= 0.85 and s["motp_mm"] <= 100, s
    assert s["mismatches"] == 0, s
    assert "MOTA" in r.stdout

"""The pipeline on a simulated recording, scored against its ground truth."""
import json

import pytest

from tests.conftest import simulated, smartroom

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    return simulated(tmp_path_factory, "walk1", 2)


def test_run_and_eval_reconstruction(walk, tmp_path):
    out = tmp_path / "out"
    r = smartroom("run", "--recording", walk, "--headless", "--out", out, "--set", "recorder.voxels=true",
                  "--set", "reconstruction.voxel_size=0.05", timeout=300)
    assert r.returncode == 0, r.stderr
    stats = json.loads((out / "stats.json").read_text())
    assert stats["stages"]["reconstruction"]["frames_out"] >= 45
    r = smartroom("eval", "--recording", walk, "--results", out)
    assert r.returncode == 0, r.stderr
    rec = json.loads((out / "eval.json").read_text())["reconstruction"]["summary"]
    assert rec["frames"] >= 45
    assert rec["recall"] > 0.9, rec
    assert rec["shadow_target_met"], rec
    assert "recall" in r.stdout


def test_eval_needs_something_to_score(walk, tmp_path):
    (tmp_path / "empty").mkdir()
    r = smartroom("eval", "--recording", walk, "--results", tmp_path / "empty")
    assert r.returncode == 2 and "holds nothing this version can score" in r.stderr

"""``smartroom bench pose --replay``: the pose stage again over a pipeline run's own voxels,
per filter seed. With the run's seed it must give the run's poses (what ``smartroom eval``
scores); other seeds give the spread a pose change is measured against."""
import json

import pytest

from tests.conftest import simulated, smartroom

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def run_with_voxels(tmp_path_factory):
    """(recording, results) of the default pipeline on 4 s of meeting3, voxels kept."""
    rec = simulated(tmp_path_factory, "meeting3", 4)
    out = tmp_path_factory.mktemp("run") / "out"
    r = smartroom("run", "--recording", rec, "--headless", "--no-pace", "--set", "recorder.voxels=true",
                  "--out", out, timeout=240)
    assert r.returncode == 0, r.stderr
    return rec, out


def test_the_runs_own_seed_gives_the_runs_poses_and_other_seeds_the_spread(run_with_voxels, tmp_path):
    rec, out = run_with_voxels
    r = smartroom("eval", "--recording", rec, "--results", out, timeout=120)
    assert r.returncode == 0, r.stderr
    pose = json.loads((out / "eval.json").read_text())["pose"]
    r = smartroom("bench", "pose", "--replay", out, "--recording", rec, "--pose-seeds", 3, "--out", tmp_path / "b",
                  timeout=300)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    rows = [line.split() for line in lines if len(line.split()) == 6 and line.split()[0].isdigit()]
    assert [int(row[0]) for row in rows] == [0, 1, 2], r.stdout
    mmta, mmtp = float(rows[0][1]), float(rows[0][2])
    # eval reads the joints rounded to 0.1 mm; the replay has them exact
    assert abs(mmta - pose["mmta"]) <= 0.002 and abs(mmtp - pose["mmtp_mm"]) <= 0.5, (rows[0], pose)
    assert 0.6 < min(float(row[1]) for row in rows) and "3 seed(s) over 100 frames: MMTA mean" in r.stdout


def test_bad_replays_are_one_line_errors(run_with_voxels, tmp_path):
    rec, out = run_with_voxels
    r = smartroom("bench", "pose", "--replay", out, "--recording", rec, "--pose-set", "nonsense=1",
                  "--out", tmp_path / "b", timeout=120)
    assert r.returncode != 0 and "unknown parameter 'nonsense'" in r.stderr and "Traceback" not in r.stderr
    r = smartroom("bench", "pose", "--replay", out, "--recording", rec, "--pose-set", "voxels=some",
                  "--out", tmp_path / "b2", timeout=120)
    assert r.returncode != 0 and "voxels = 'some' is not one of" in r.stderr and "Traceback" not in r.stderr
    r = smartroom("bench", "pose", "--replay", tmp_path, "--recording", rec, "--out", tmp_path / "c", timeout=120)
    assert r.returncode != 0 and "layout.yaml: file not found" in r.stderr and "Traceback" not in r.stderr

"""People of every stature, still, gesturing in place and seated (issue 22), through the
real worker processes over zenoh: the statures3 scene (1.50 m gesturing in place, 1.95 m
walking and crouching, 1.62 m sitting down), scored against its ground truth with the
accuracy benchmark's scoring (app.benchmarks.accuracy.score_scene)."""
import json

import pytest

from app.benchmarks.accuracy import score_scene
from tests.conftest import simulated, smartroom

pytestmark = pytest.mark.integration

SECONDS = 8


@pytest.fixture(scope="module")
def scored(tmp_path_factory):
    rec = simulated(tmp_path_factory, "statures3", SECONDS)
    out = tmp_path_factory.mktemp("statures") / "out"
    r = smartroom("run", "--recording", rec, "--headless", "--no-pace", "--out", out, timeout=400)
    assert r.returncode == 0, r.stderr
    assert json.loads((out / "stats.json").read_text())["complete"]
    return score_scene(rec, out)


def test_every_stature_is_tracked_and_nobody_is_untracked_for_a_second(scored):
    assert scored["statures"] == {"1": 1.5, "2": 1.95, "3": 1.62}
    assert all(s <= 1.0 for s in scored["untracked_s"].values()), scored["untracked_s"]
    t = scored["tracking"]
    assert t["misses"] <= 0.03 * t["truths"] and t["mismatches"] <= 1, t
    assert t["mota"] >= 0.9 and t["idf1"] >= 0.9 and t["motp_mm"] <= 60, t
    for band, (hit, frames) in scored["detection_by_stature"].items():
        assert frames == 0 or hit / frames >= 0.95, (band, hit, frames)


def test_a_person_gesturing_in_place_and_a_seated_person_are_found(scored):
    act = scored["detection_by_activity"]
    for what in ("gesturing", "sitting"):
        hit, frames = act[what]
        assert frames > 25 and hit / frames >= 0.9, (what, act)


def test_every_person_is_posed(scored):
    """The 1.50 m person gestures in place from the first frame: no walking direction
    tells the filter which way they face, and which way it settles is the filter seed's
    luck (replays of one run, 8 filter seeds: MMTA 0.716-0.870 with the crown, mean
    0.793; 0.701-0.768 without, mean 0.748; the default seed 0 faces them backwards for
    half the clip, 0.722). The bound holds whichever way they are faced."""
    p = scored["pose"]
    assert p["frames_scored"] >= 190 and p["mmta"] >= 0.70 and p["mpjpe_mm"] <= 120, p


def test_no_phantom_is_tracked_or_posed(scored):
    """Where the cones of the 1.50 m and the 1.62 m person cross above the table, a blob
    the tree calls a person held a track for 63 frames before the ghost test."""
    assert scored["phantom_poses"] == 0 and not scored["phantom_tracks"], scored
